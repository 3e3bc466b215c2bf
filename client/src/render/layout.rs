//! Where the tiles lie: their size, spacing and the terrain's edge.

use terrain_shared::TileId;

/// The terrain's geometry: enough to place any tile.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Layout {
    pub tile_size: u32,
    /// Metres between samples, east and south.
    pub spacing_m: [f64; 2],
    /// Metres the real samples span, east and south, from sample (0, 0): the terrain's edge.
    /// The last tiles of a row or column are padded past it (the manifest's `valid`), and
    /// nothing past it is drawn.
    pub extent_m: [f64; 2],
}

impl Layout {
    /// The layout of `manifest`'s tiles.
    pub fn of(manifest: &terrain_shared::Manifest) -> Layout {
        Layout {
            tile_size: manifest.tile_size,
            spacing_m: manifest.spacing_m,
            extent_m: manifest.extent_m,
        }
    }

    /// Metres a tile of level 0 spans, east and south.
    pub fn tile_extent_m(&self) -> [f64; 2] {
        self.tile_extent_m_at(0)
    }

    /// Metres a tile of `level` spans, east and south: `2^level` times level 0's.
    pub fn tile_extent_m_at(&self, level: u32) -> [f64; 2] {
        let cells = f64::from(self.tile_size - 1);
        let spacing = self.spacing_at(level);
        [cells * spacing[0], cells * spacing[1]]
    }

    /// Metres between the samples of `level`, east and south.
    pub fn spacing_at(&self, level: u32) -> [f64; 2] {
        let scale = f64::from(1u32 << level.min(31));
        [self.spacing_m[0] * scale, self.spacing_m[1] * scale]
    }

    /// Level-0 samples between two samples of `level`.
    pub fn sample_step(level: u32) -> f64 {
        f64::from(1u32 << level.min(31))
    }

    /// World position of a tile's sample (0, 0), metres.
    pub fn tile_origin_m(&self, id: TileId) -> [f64; 2] {
        let e = self.tile_extent_m_at(id.level);
        [f64::from(id.x) * e[0], f64::from(id.y) * e[1]]
    }
}
