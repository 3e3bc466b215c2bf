//! The whole data path over a real socket: the jacksboro fixture is built into a database,
//! served on 127.0.0.1:0 and fetched back through the client; every height must equal the
//! source raster and every texture level must be the image the manifest promises.

use terrain_client::fetch::{FetchError, TileClient};
use terrain_shared::{Heights, TileId};
use terrain_tests::data::{build_jacksboro, jacksboro, png_codes};
use terrain_tests::server::TestServer;

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("tokio runtime")
}

#[test]
fn every_height_served_for_jacksboro_equals_the_source_raster() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let report = build_jacksboro(tmp.path());
    let server = TestServer::start(&report.out);
    let (width, height, source) = png_codes(&jacksboro());

    runtime().block_on(async {
        let client = TileClient::new(server.base_url()).expect("client");
        let manifest = client.manifest().await.expect("manifest");
        assert_eq!(
            manifest, report.manifest,
            "the served manifest is the built one"
        );
        let n = manifest.tile_size;
        let mut real_samples = 0usize;
        for record in &manifest.tiles {
            let id = record.id();
            let tile: Heights = client
                .heights(&manifest, id)
                .await
                .unwrap_or_else(|e| panic!("tile {id}: {e}"));
            for y in 0..n {
                for x in 0..n {
                    let (sx, sy) = (id.x * (n - 1) + x, id.y * (n - 1) + y);
                    let expected =
                        source[(sy.min(height - 1) * width + sx.min(width - 1)) as usize];
                    assert_eq!(
                        tile.codes[(y * n + x) as usize],
                        expected,
                        "tile {id} sample ({x}, {y})"
                    );
                    assert_eq!(
                        tile.metres(x as usize, y as usize),
                        f64::from(expected),
                        "1 m per code, offset 0"
                    );
                    if sx < width && sy < height {
                        real_samples += 1;
                    }
                }
            }
            assert_eq!(
                record.valid,
                [
                    (width - id.x * (n - 1)).min(n),
                    (height - id.y * (n - 1)).min(n)
                ]
            );
            for level in 0..manifest.texture.levels {
                let bytes = client
                    .texture(&manifest, id, level)
                    .await
                    .unwrap_or_else(|e| panic!("tile {id} level {level}: {e}"));
                let image = image::load_from_memory_with_format(&bytes, image::ImageFormat::Jpeg)
                    .expect("a JPEG");
                let side = manifest.texture.level_size(level);
                assert_eq!(
                    (image.width(), image.height()),
                    (side, side),
                    "tile {id} level {level}"
                );
            }
        }
        // Every raster sample was compared at least once (shared borders more than once).
        assert!(
            real_samples >= (width * height) as usize,
            "{real_samples} samples compared"
        );
    });
}

#[test]
fn a_tile_outside_the_grid_or_a_bad_url_is_a_clear_client_error() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let report = build_jacksboro(tmp.path());
    let server = TestServer::start(&report.out);
    runtime().block_on(async {
        let client = TileClient::new(server.base_url()).expect("client");
        let manifest = client.manifest().await.expect("manifest");
        let outside = client.heights(&manifest, TileId::new(99, 0)).await;
        assert!(
            matches!(outside, Err(FetchError::NotInGrid { .. })),
            "{outside:?}"
        );
        // A manifest from another build names another content version: the server says 404 and why.
        let mut stale = manifest.clone();
        stale.content_version = "0123456789abcdef".into();
        let error = client
            .heights(&stale, TileId::new(0, 0))
            .await
            .expect_err("stale version");
        let message = error.to_string();
        assert!(
            message.contains("404") && message.contains(&manifest.content_version),
            "{message}"
        );
    });
}

#[test]
fn a_corrupt_or_truncated_tile_body_is_rejected_by_the_decoder() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let report = build_jacksboro(tmp.path());
    let server = TestServer::start(&report.out);
    runtime().block_on(async {
        let client = TileClient::new(server.base_url()).expect("client");
        let manifest = client.manifest().await.expect("manifest");
        let body = client
            .heights_bytes(&manifest, TileId::new(1, 1))
            .await
            .expect("served bytes");
        assert!(Heights::decode(&body).is_ok());
        for cut in [0, 10, 44, body.len() / 2, body.len() - 1] {
            assert!(
                Heights::decode(&body[..cut]).is_err(),
                "truncated to {cut} bytes"
            );
        }
        for position in [5, 20, 40, 60, body.len() / 2, body.len() - 1] {
            let mut corrupt = body.to_vec();
            corrupt[position] ^= 0x10;
            assert!(
                Heights::decode(&corrupt).is_err(),
                "byte {position} flipped"
            );
        }
    });
}
