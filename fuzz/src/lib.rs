//! What each fuzz target feeds to which entry point, as plain functions of the input bytes:
//! the `fuzz_targets/` binaries call them under libFuzzer, and the end-to-end tests
//! (`tests/e2e/fuzz_corpora.rs`) include this file to replay every committed input on stable.
//!
//! Each function returns normally for any input. Errors are expected and ignored; a panic,
//! a hang or an allocation past libFuzzer's limit is a bug in the code under test. Where an
//! input is accepted, the function also checks what the rest of the system relies on.

use std::path::Path;
use terrain_server::build::input::{self, Format, OutOfRange, ReadOptions};
use terrain_shared::heights::Coder;
use terrain_shared::{Blob, Heights, Manifest, TileBlob, TileId, mask};

/// Bytes of the heights header (see `terrain_shared::heights`); the payload follows it.
const HEIGHTS_HEADER: usize = 44;

/// `Heights::decode`, twice: on the input as it is, and with its payload length and
/// checksum made right, so that the checks and the decoding behind the checksum are reached
/// (random bytes almost never carry a valid CRC-32). A tile that decodes must survive an
/// encode and decode unchanged. The input also goes through `TileBlob::decode` (what the
/// heights route serves wraps the heights in a tile blob), as it is and wrapped in a tile
/// blob, which must give the heights back.
pub fn heights_decode(data: &[u8]) {
    let _ = Heights::decode(data);
    if let Ok(blob) = TileBlob::decode(data) {
        assert_eq!(
            TileBlob::decode(&blob.encode()),
            Ok(blob),
            "a tile blob round trips"
        );
    }
    let wrapped = TileBlob {
        mask_errors_m: vec![0.0, 0.5],
        texture: vec![Blob::of(b"coarsest")],
        heights: data.to_vec(),
    }
    .encode();
    let head = TileBlob::head(&wrapped).expect("a tile blob made here splits");
    assert_eq!(
        &wrapped[head.heights_at..],
        data,
        "the heights come back whole"
    );
    if data.len() < HEIGHTS_HEADER {
        return;
    }
    let mut sealed = data.to_vec();
    let payload_len = (data.len() - HEIGHTS_HEADER) as u32;
    sealed[36..40].copy_from_slice(&payload_len.to_le_bytes());
    let mut crc = crc32fast::Hasher::new();
    crc.update(&sealed[..40]);
    crc.update(&sealed[HEIGHTS_HEADER..]);
    sealed[40..HEIGHTS_HEADER].copy_from_slice(&crc.finalize().to_le_bytes());
    if let Ok(tile) = Heights::decode(&sealed) {
        for coder in [Coder::Rans, Coder::Zstd(1)] {
            let again = tile.encode_with(coder).expect("a decoded tile encodes");
            assert_eq!(
                Heights::decode(&again).expect("a re-encoded tile decodes"),
                tile,
                "{coder:?}"
            );
        }
    }
}

/// `Manifest::from_json`, then what a client does with a manifest it accepted: looks tiles
/// up, places samples, sizes texture levels and mask index sets, serialises it again.
pub fn manifest_parse(data: &[u8]) {
    let Ok(manifest) = Manifest::from_json(data) else {
        return;
    };
    let n = manifest.tile_size;
    for (dense, (id, record)) in manifest.tiles().enumerate() {
        assert_eq!(
            manifest.index(id),
            Some(dense),
            "tile {id} is where the order says"
        );
        assert_eq!(manifest.id_at(dense), id);
        assert!(
            manifest.tile(id).is_some_and(|r| std::ptr::eq(r, record)),
            "tile {id} is in its own grid"
        );
        let valid = manifest.valid(id);
        assert!(
            (1..=n).contains(&valid[0]) && (1..=n).contains(&valid[1]),
            "tile {id} has {valid:?} real samples"
        );
        for child in manifest.children(id) {
            assert_eq!(child.parent(), id, "tile {id} covers its children");
        }
        let _ = manifest.sample_position_m(id, n - 1, n - 1);
    }
    assert_eq!(manifest.tiles().count(), manifest.tile_count());
    for level in 0..manifest.level_count() {
        let grid = manifest.grid(level);
        let _ = manifest.tile(TileId::at(level, grid.columns, grid.rows));
        let _ = manifest.tile(TileId::at(level, u32::MAX, u32::MAX));
    }
    assert!(
        manifest
            .tile(TileId::at(manifest.level_count(), 0, 0))
            .is_none()
    );
    for level in 0..manifest.texture.levels.min(64) {
        let _ = manifest.texture.level_size(level);
    }
    let _ = mask::kept_indices(n, 0);
    let _ = mask::kept_indices(n, manifest.mask_levels.saturating_sub(1));
    let _ = manifest.compute_content_version();
    Manifest::from_json(&manifest.to_json()).expect("a valid manifest survives its own JSON");
}

/// The builder's PNG reader on the input as a file's bytes.
pub fn read_png(data: &[u8]) {
    read(data, Format::Png, Path::new("fuzz.png"));
}

/// The builder's GeoTIFF reader on the input as a file's bytes.
pub fn read_geotiff(data: &[u8]) {
    read(data, Format::GeoTiff, Path::new("fuzz.tif"));
}

/// The builder's `.hgt` reader. The input is a file name (which gives the corner), a
/// newline, then the file's bytes. Only two lengths are valid and every 16-bit value is a
/// sample, so what can go wrong is in the name and the length; full-size files are the
/// end-to-end tests' (`an_srtm_hgt_file_gives_the_same_heights_as_its_geotiff`).
pub fn read_hgt(data: &[u8]) {
    let split = data.iter().position(|&b| b == b'\n').unwrap_or(data.len());
    let (name, rest) = data.split_at(split);
    let name = String::from_utf8_lossy(name);
    read(
        rest.get(1..).unwrap_or_default(),
        Format::Hgt,
        Path::new(&*name),
    );
}

/// Reads with the builder's defaults, then, when samples were refused for being out of
/// range, again with them taken as no-data. Checks what the builder relies on.
fn read(bytes: &[u8], format: Format, path: &Path) {
    let mut options = ReadOptions {
        nodata: None,
        float_quantum_m: 0.01,
        out_of_range: OutOfRange::Refuse,
    };
    let mut result = input::decode_heights(bytes, format, path, &options);
    if let Err(input::InputError::OutOfRange { .. }) = result {
        options.out_of_range = OutOfRange::Nodata;
        result = input::decode_heights(bytes, format, path, &options);
    }
    let Ok(raster) = result else {
        return;
    };
    let samples = raster.width as usize * raster.height as usize;
    assert!(raster.width >= 2 && raster.height >= 2);
    assert_eq!(raster.codes.len(), samples);
    assert!(raster.voids.is_empty() || raster.voids.len() == samples);
    assert!(raster.voids.is_empty() || raster.voids.iter().any(|&v| !v));
    assert!(raster.quantum_m.is_finite() && raster.quantum_m > 0.0);
}
