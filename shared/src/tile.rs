//! Tile identity: a column and a row in the tile grid, row 0 at the north edge.

use serde::{Deserialize, Serialize};
use std::fmt;

/// One tile of the grid: `x` counts columns from the west edge, `y` rows from the north edge.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub struct TileId {
    pub x: u32,
    pub y: u32,
}

impl TileId {
    pub const fn new(x: u32, y: u32) -> Self {
        Self { x, y }
    }

    /// Chebyshev distance in tiles: the belt index of `other` around `self`.
    pub fn belt_distance(self, other: TileId) -> u32 {
        self.x.abs_diff(other.x).max(self.y.abs_diff(other.y))
    }
}

impl fmt::Display for TileId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}/{}", self.x, self.y)
    }
}
