//! Writes the seed inputs of every fuzz target into `fuzz/corpus/<target>/seed-*`: small crops of the
//! bundled jacksboro DEM and of an SRTM GeoTIFF of the data kit, in each format the
//! builder reads, plus a tile and a manifest the builder itself made. libFuzzer mutates
//! them; starting from real files reaches deep into the decoders at once.
//!
//! `cargo run --release -p terrain-server --example fuzz_seeds -- [SRTM.tif]` (the GeoTIFF
//! is optional; without it the int16 GeoTIFF seed is cut from jacksboro instead).

use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use terrain_server::build::{BuildOptions, build};
use terrain_shared::Heights;
use tiff::encoder::{TiffEncoder, colortype};
use tiff::tags::Tag;

fn main() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let dem = root.join("tests/fixtures/jacksboro/jacksboro_fault_dem.png");
    let grey = image::open(&dem).expect("jacksboro").into_luma16();
    let crop = |x: u32, y: u32, w: u32, h: u32| -> Vec<u16> {
        (y..y + h)
            .flat_map(|j| (x..x + w).map(move |i| (i, j)))
            .map(|(i, j)| grey.get_pixel(i, j).0[0])
            .collect()
    };
    let corpus = |target: &str| {
        let dir = root.join("fuzz/corpus").join(target);
        std::fs::create_dir_all(&dir).expect("corpus dir");
        dir
    };
    let write = |dir: &PathBuf, name: &str, bytes: &[u8]| {
        std::fs::write(dir.join(format!("seed-{name}")), bytes).expect("write seed");
    };

    // PNG: 16-bit and 8-bit greyscale crops, and the smallest raster the builder takes.
    let png = corpus("read_png");
    for (name, w, h) in [("16bit-16x12", 16, 12), ("16bit-2x2", 2, 2)] {
        let image = image::ImageBuffer::<image::Luma<u16>, _>::from_raw(w, h, crop(100, 100, w, h))
            .expect("crop");
        write(&png, &format!("{name}.png"), &encode_png(image.into()));
    }
    let eight: Vec<u8> = crop(200, 50, 16, 8)
        .iter()
        .map(|&v| (v >> 8) as u8)
        .collect();
    let image = image::GrayImage::from_raw(16, 8, eight).expect("crop");
    write(&png, "8bit-16x8.png", &encode_png(image.into()));

    // GeoTIFF: int16 with a geotransform, EPSG:4326 and a GDAL no-data tag; uint16; float32
    // with fractions and a NaN; float64.
    let tif = corpus("read_geotiff");
    let samples: Vec<i16> = match std::env::args().nth(1) {
        Some(srtm) => srtm_crop(Path::new(&srtm), 16, 12),
        None => crop(100, 100, 16, 12).iter().map(|&v| v as i16).collect(),
    };
    write(&tif, "int16-geo.tif", &geotiff_i16(&samples, 16, 12));
    let u: Vec<u16> = crop(10, 10, 8, 8);
    write(&tif, "uint16.tif", &tiff_of::<colortype::Gray16>(&u, 8, 8));
    let mut f: Vec<f32> = crop(50, 50, 8, 6)
        .iter()
        .map(|&v| f32::from(v) / 7.0)
        .collect();
    f[3] = f32::NAN;
    write(
        &tif,
        "float32.tif",
        &tiff_of::<colortype::Gray32Float>(&f, 8, 6),
    );
    let d: Vec<f64> = crop(60, 60, 4, 4)
        .iter()
        .map(|&v| f64::from(v) * 0.25)
        .collect();
    write(
        &tif,
        "float64.tif",
        &tiff_of::<colortype::Gray64Float>(&d, 4, 4),
    );

    // .hgt: a name, a newline, then big-endian int16 samples (see `read_hgt` in src/lib.rs).
    let hgt = corpus("read_hgt");
    let be: Vec<u8> = crop(0, 0, 16, 4)
        .iter()
        .flat_map(|&v| (v as i16).to_be_bytes())
        .collect();
    write(
        &hgt,
        "full-size",
        &[b"+N46W122.hgt\n".as_slice(), &be].concat(),
    );
    write(&hgt, "short", &[b"S10E005.hgt\n".as_slice(), &be].concat());

    // Heights: tiles of the codec, as the builder encodes them (version 2, rANS), and as
    // version 1 (zstd) did, from 1 to 4 byte planes.
    let heights = corpus("heights_decode");
    for (name, side, scale) in [
        ("17x17", 17u16, 1i32),
        ("5x5-3planes", 5, 4000),
        ("2x3-4planes", 2, 1 << 22),
    ] {
        let s = u32::from(side);
        let codes = crop(150, 150, s, s)
            .iter()
            .map(|&v| i32::from(v) * scale - 7)
            .collect();
        let tile = Heights {
            width: side,
            height: side,
            quantum_m: 0.1,
            offset_m: -5.0,
            codes,
        };
        write(&heights, name, &tile.encode().expect("encodes"));
        write(
            &heights,
            &format!("{name}-zstd"),
            &tile.encode_with_level(19).expect("encodes"),
        );
    }

    // Manifest: what the builder writes for a 9x5 crop cut into two 5x5 tiles.
    let tmp = tempfile::tempdir().expect("tempdir");
    let small = tmp.path().join("small.png");
    image::ImageBuffer::<image::Luma<u16>, _>::from_raw(9, 5, crop(120, 80, 9, 5))
        .expect("crop")
        .save(&small)
        .expect("png");
    let mut options = BuildOptions::new(&small, tmp.path().join("db"));
    options.tile_size = 5;
    let report = build(&options, &|_, _| {}, &AtomicBool::new(false)).expect("builds");
    write(
        &corpus("manifest_parse"),
        "2-tiles.json",
        &report.manifest.to_json(),
    );
}

fn encode_png(image: image::DynamicImage) -> Vec<u8> {
    let mut bytes = std::io::Cursor::new(Vec::new());
    image
        .write_to(&mut bytes, image::ImageFormat::Png)
        .expect("png");
    bytes.into_inner()
}

fn tiff_of<C: colortype::ColorType>(samples: &[C::Inner], w: u32, h: u32) -> Vec<u8>
where
    [C::Inner]: tiff::encoder::TiffValue,
{
    let mut bytes = std::io::Cursor::new(Vec::new());
    TiffEncoder::new(&mut bytes)
        .expect("encoder")
        .write_image::<C>(w, h, samples)
        .expect("tiff");
    bytes.into_inner()
}

fn geotiff_i16(samples: &[i16], w: u32, h: u32) -> Vec<u8> {
    let mut bytes = std::io::Cursor::new(Vec::new());
    let mut encoder = TiffEncoder::new(&mut bytes).expect("encoder");
    let mut image = encoder
        .new_image::<colortype::GrayI16>(w, h)
        .expect("image");
    let dir = image.encoder();
    let step = 1.0 / 1200.0;
    dir.write_tag(Tag::ModelPixelScaleTag, &[step, step, 0.0][..])
        .expect("scale");
    dir.write_tag(
        Tag::ModelTiepointTag,
        &[0.0, 0.0, 0.0, -122.0, 47.0, 0.0][..],
    )
    .expect("tie point");
    // GeoKeyDirectory: version 1.1.0, 2 keys; raster is area; geographic EPSG:4326.
    dir.write_tag(
        Tag::GeoKeyDirectoryTag,
        &[1u16, 1, 0, 2, 1025, 0, 1, 1, 2048, 0, 1, 4326][..],
    )
    .expect("geokeys");
    dir.write_tag(Tag::GdalNodata, "-32768").expect("nodata");
    image.write_data(samples).expect("tiff");
    bytes.into_inner()
}

fn srtm_crop(path: &Path, w: u32, h: u32) -> Vec<i16> {
    let file = std::fs::File::open(path).expect("SRTM GeoTIFF");
    let mut decoder = tiff::decoder::Decoder::new(std::io::BufReader::new(file)).expect("tiff");
    let (width, _) = decoder.dimensions().expect("dimensions");
    let tiff::decoder::DecodingResult::I16(all) = decoder.read_image().expect("decodes") else {
        panic!("{}: not int16", path.display());
    };
    // From the first rows, 400 samples in.
    (0..h)
        .flat_map(|y| (0..w).map(move |x| (x, y)))
        .map(|(x, y)| all[(y * width + x + 400) as usize])
        .collect()
}
