//! `terrain-server export`: a database's XYZ pyramid as one PMTiles v3 archive, for hosting
//! as a static file (object storage, a CDN) and reading with MapLibre's PMTiles protocol.
//! Written to a temporary name beside the output and renamed into place when complete; or,
//! for an object-store key (`--pmtiles s3://bucket/key.pmtiles`), written to a temporary file
//! and uploaded in parts, the object appearing only when the upload completes.

use crate::db::{TileDb, Verify};
use crate::web::index::Kind;
use anyhow::{Context, bail};
use std::path::PathBuf;

/// Arguments of `terrain-server export`.
#[derive(Debug, clap::Args)]
pub struct ExportArgs {
    /// Tile database directory (built from a georeferenced source, with web tiles).
    pub db: PathBuf,
    /// Write the pyramid as a PMTiles v3 archive to this file, or to this object of an
    /// object store (`s3://bucket/key.pmtiles`, credentials and endpoint from the AWS_*
    /// environment variables).
    #[arg(long, value_name = "FILE|s3://BUCKET/KEY", value_parser = crate::store::Location::parse)]
    pub pmtiles: crate::store::Location,
    /// Which pyramid: the heights as Terrarium or Terrain-RGB PNGs, or the texture.
    #[arg(long, value_enum, default_value_t = Pyramid::Terrarium)]
    pub pyramid: Pyramid,
    /// Replace an existing file.
    #[arg(long)]
    pub force: bool,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Pyramid {
    Terrarium,
    TerrainRgb,
    Texture,
}

/// What an export wrote.
#[derive(Debug)]
pub struct Exported {
    pub tiles: usize,
    pub bytes: u64,
}

/// Writes the archive; see [`ExportArgs`].
pub fn export(args: &ExportArgs) -> anyhow::Result<Exported> {
    use crate::store::Location;
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    let exists = match &args.pmtiles {
        Location::Dir(path) => path.exists(),
        Location::Store(url) => runtime.block_on(async {
            use object_store::ObjectStoreExt as _;
            let store = crate::store::connect(url)?;
            match store.head(&url.prefix).await {
                Ok(_) => Ok(true),
                Err(object_store::Error::NotFound { .. }) => Ok(false),
                Err(e) => Err(anyhow::Error::new(e).context(format!("cannot look for {url}"))),
            }
        })?,
    };
    if exists && !args.force {
        bail!("{} exists; give --force to replace it", args.pmtiles);
    }
    let db = TileDb::open(&args.db, Verify::Hashes)
        .with_context(|| format!("cannot open {}", args.db.display()))?;
    let manifest = db.manifest();
    let Some(info) = &manifest.web else {
        bail!(
            "{} has no web tiles: its source is not georeferenced, or it was built with --no-web",
            args.db.display()
        );
    };
    let kind = match args.pyramid {
        Pyramid::Terrarium => Kind::Terrarium,
        Pyramid::TerrainRgb => Kind::TerrainRgb,
        Pyramid::Texture => Kind::Texture,
    };
    let mut tiles: Vec<(u64, pmtiles::TileCoord, &bytes::Bytes)> = Vec::new();
    for (entry, blob) in db.web_tiles().filter(|(e, _)| e.kind == kind) {
        let coord = pmtiles::TileCoord::new(entry.z as u8, entry.x, entry.y)
            .with_context(|| format!("tile {}/{}/{}", entry.z, entry.x, entry.y))?;
        tiles.push((pmtiles::TileId::from(coord).value(), coord, &blob.bytes));
    }
    tiles.sort_by_key(|t| t.0);
    let [w, s, e, n] = info.bounds_deg;
    let metadata = serde_json::json!({
        "name": manifest.dataset,
        "format": "png",
        "type": "baselayer",
        "encoding": match args.pyramid {
            Pyramid::Terrarium => "terrarium",
            Pyramid::TerrainRgb => "mapbox",
            Pyramid::Texture => "rgba",
        },
        "version": manifest.content_version,
        "tileSize": info.xyz_tile_size,
    });
    let dir = match &args.pmtiles {
        Location::Dir(out) => match out.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
            _ => PathBuf::from("."),
        },
        Location::Store(_) => std::env::temp_dir(),
    };
    let mut builder = tempfile::Builder::new();
    builder.prefix(".export-").suffix(".pmtiles.part");
    // A temporary file is made 0600; the archive is for web servers running as other users,
    // so it is made as any new file is: 0666 less the umask (0644 under 0022).
    #[cfg(unix)]
    builder.permissions(std::os::unix::fs::PermissionsExt::from_mode(0o666));
    let tmp = builder
        .tempfile_in(&dir)
        .with_context(|| format!("cannot write in {}", dir.display()))?;
    let file = tmp.reopen().context("cannot reopen the temporary file")?;
    let mut writer = pmtiles::PmTilesWriter::new(pmtiles::TileType::Png)
        .min_zoom(0)
        .max_zoom(info.xyz_max_zoom as u8)
        .bounds(w, s, e, n)
        .center((w + e) / 2.0, (s + n) / 2.0)
        .center_zoom(info.xyz_max_zoom.saturating_sub(2) as u8)
        .metadata(metadata.to_string())
        .create(std::io::BufWriter::new(file))
        .context("cannot start the archive")?;
    for (_, coord, bytes) in &tiles {
        writer
            .add_tile(*coord, bytes)
            .context("cannot write a tile")?;
    }
    writer.finalize().context("cannot finish the archive")?;
    tmp.as_file()
        .sync_all()
        .context("cannot sync the archive")?;
    let bytes = tmp.as_file().metadata().map(|m| m.len()).unwrap_or(0);
    match &args.pmtiles {
        Location::Dir(out) => {
            tmp.persist(out)
                .with_context(|| format!("cannot rename the archive to {}", out.display()))?;
        }
        Location::Store(url) => {
            runtime
                .block_on(async {
                    let store = crate::store::connect(url)?;
                    crate::store::upload_file(&*store, tmp.path(), &url.prefix, &|_| {}).await
                })
                .with_context(|| format!("cannot upload the archive to {url}"))?;
        }
    }
    Ok(Exported {
        tiles: tiles.len(),
        bytes,
    })
}

/// Runs `terrain-server export` and prints what it wrote.
pub fn run_cli(args: ExportArgs) -> anyhow::Result<()> {
    let done = export(&args)?;
    crate::print_stdout(&format!(
        "wrote {} ({} tiles, {:.2} MiB)\n",
        args.pmtiles,
        done.tiles,
        done.bytes as f64 / (1024.0 * 1024.0)
    ))
    .context("cannot write to stdout")?;
    Ok(())
}
