//! URL paths of the tile API, built in one place for the server's router and the client.
//!
//! Tile paths carry the manifest's `content_version`: a rebuilt database gets new tile
//! URLs, so a tile URL always names the same bytes and caches may keep it forever.

use crate::tile::TileId;

/// Prefix of every versioned route; bumped only with an incompatible API change.
pub const API_PREFIX: &str = "/v1";
/// The manifest, revalidated by clients and caches (it changes when the database does).
pub const MANIFEST: &str = "/v1/manifest.json";
pub const HEALTHZ: &str = "/healthz";
pub const METRICS: &str = "/metrics";

/// Path of the tile blob (`crate::tile_blob`: mask errors, texture hashes, heights) of one
/// tile of any level of the pyramid.
pub fn heights(content_version: &str, id: TileId) -> String {
    format!(
        "{API_PREFIX}/{content_version}/levels/{}/tiles/{}/{}/heights",
        id.level, id.x, id.y
    )
}

/// Path of the quadtree patch of tile `id` ([`crate::quadtree`]).
pub fn patch(content_version: &str, id: TileId) -> String {
    format!(
        "{API_PREFIX}/{content_version}/levels/{}/tiles/{}/{}/patch",
        id.level, id.x, id.y
    )
}

/// Path of the patch index.
pub fn patch_index(content_version: &str) -> String {
    format!("{API_PREFIX}/{content_version}/patches/index")
}

/// Path of one texture level (0 = coarsest) of one tile.
pub fn texture(content_version: &str, id: TileId, level: u32) -> String {
    format!(
        "{API_PREFIX}/{content_version}/levels/{}/tiles/{}/{}/texture/{level}",
        id.level, id.x, id.y
    )
}
