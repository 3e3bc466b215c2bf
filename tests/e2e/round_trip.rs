//! The whole data path over a real socket: the jacksboro fixture is built into a database,
//! served on 127.0.0.1:0 and fetched back through the client; every height of every level
//! of the pyramid must equal the source raster's sample it stands on, and every texture
//! level must match its tile blob's hash and be the image the manifest promises.

use terrain_client::http_client::{FetchError, TileClient, decode_tile};
use terrain_shared::{Heights, TileBlob, TileId};
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
        assert!(manifest.level_count() > 1, "jacksboro makes a pyramid");
        let n = manifest.tile_size;
        let mut real_samples = 0usize;
        let mut tiles = 0;
        for (id, record) in manifest.tiles() {
            let tile = client
                .tile(&manifest, id)
                .await
                .unwrap_or_else(|e| panic!("tile {id}: {e}"));
            // A tile of level k keeps every 2^k-th sample of level 0; samples past its
            // level's raster repeat the last real one, as at level 0.
            let raster = manifest.levels[id.level as usize].raster;
            for y in 0..n {
                for x in 0..n {
                    let (lx, ly) = (
                        (id.x * (n - 1) + x).min(raster.width - 1),
                        (id.y * (n - 1) + y).min(raster.height - 1),
                    );
                    let (sx, sy) = (
                        (lx << id.level).min(width - 1),
                        (ly << id.level).min(height - 1),
                    );
                    let expected = source[(sy * width + sx) as usize];
                    assert_eq!(
                        tile.heights.codes[(y * n + x) as usize],
                        expected,
                        "tile {id} sample ({x}, {y})"
                    );
                    assert_eq!(
                        tile.heights.metres(x as usize, y as usize),
                        f64::from(expected),
                        "1 m per code, offset 0"
                    );
                    if id.level == 0 && x < width - id.x * (n - 1) && y < height - id.y * (n - 1) {
                        real_samples += 1;
                    }
                }
            }
            assert_eq!(
                manifest.valid(id),
                [
                    (raster.width - id.x * (n - 1)).min(n),
                    (raster.height - id.y * (n - 1)).min(n)
                ],
                "tile {id}"
            );
            assert_eq!(tile.mask_errors_m.len(), manifest.mask_levels as usize);
            // Every texture level verified against the tile blob's table (whose hash the
            // manifest gave), and the image the manifest promises.
            assert_eq!(
                tile.texture.len(),
                manifest.texture.levels as usize,
                "tile {id}"
            );
            assert_eq!(
                tile.texture[0].bytes, record.coarsest_texture_bytes,
                "tile {id}"
            );
            for level in 0..manifest.texture.levels {
                let blob = &tile.texture[level as usize];
                let bytes = client
                    .texture(&manifest, id, level, Some(blob))
                    .await
                    .unwrap_or_else(|e| panic!("tile {id} level {level}: {e}"));
                assert_eq!(bytes.len() as u64, blob.bytes, "tile {id} level {level}");
                let image = image::load_from_memory_with_format(&bytes, image::ImageFormat::Jpeg)
                    .expect("a JPEG");
                let side = manifest.texture.level_size(level);
                assert_eq!(
                    (image.width(), image.height()),
                    (side, side),
                    "tile {id} level {level}"
                );
            }
            tiles += 1;
        }
        assert_eq!(tiles, manifest.tile_count(), "every tile of every level");
        // Every raster sample was compared at least once at level 0 (shared borders more
        // than once).
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
        let level_one = manifest.grid(1);
        for outside in [
            TileId::new(99, 0),
            TileId::at(1, level_one.columns, 0),
            TileId::at(manifest.level_count(), 0, 0),
        ] {
            let refused = client.tile(&manifest, outside).await;
            assert!(
                matches!(refused, Err(FetchError::NotInGrid { id, .. }) if id == outside),
                "{outside}: {refused:?}"
            );
        }
        // A manifest from another build names another content version: the server says 404 and why.
        let mut stale = manifest.clone();
        stale.content_version = "0123456789abcdef".into();
        let error = client
            .tile(&stale, TileId::new(0, 0))
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
            .tile_bytes(&manifest, TileId::new(1, 1))
            .await
            .expect("served bytes");
        let decode = |bytes: Vec<u8>| decode_tile("test".into(), bytes.into());
        let blob = TileBlob::decode(&body).expect("a tile blob");
        assert!(Heights::decode(&blob.heights).is_ok());
        assert!(decode(body.to_vec()).await.is_ok());
        let heights_at = TileBlob::head(&body).expect("a tile blob").heights_at;
        // Cut anywhere, the blob's sizes no longer add up.
        for cut in [
            0,
            10,
            heights_at - 1,
            heights_at + 44,
            body.len() / 2,
            body.len() - 1,
        ] {
            let result = decode(body[..cut].to_vec()).await;
            assert!(
                matches!(result, Err(FetchError::TileBlob { .. })),
                "truncated to {cut} bytes: {result:?}"
            );
        }
        // A byte flipped in the heights: their own checks refuse them.
        let heights_len = body.len() - heights_at;
        for position in [5, 20, 40, 60, heights_len / 2, heights_len - 1] {
            let mut corrupt = body.to_vec();
            corrupt[heights_at + position] ^= 0x10;
            let result = decode(corrupt).await;
            assert!(
                matches!(result, Err(FetchError::Decode { .. })),
                "heights byte {position} flipped: {result:?}"
            );
        }
        // The coarsest mask's error made negative (its sign bit, the last byte of its
        // little-endian f32 after the 16-byte header): refused by the blob, before the
        // heights.
        let last = blob.mask_errors_m.len() - 1;
        assert!(blob.mask_errors_m[last] > 0.0, "{:?}", blob.mask_errors_m);
        let mut corrupt = body.to_vec();
        corrupt[16 + 4 * last + 3] ^= 0x80;
        let result = decode(corrupt).await;
        assert!(
            matches!(result, Err(FetchError::TileBlob { .. })),
            "a negative mask error: {result:?}"
        );
    });
}
