//! Tile identity: a level of the pyramid, a column and a row in that level's tile grid,
//! row 0 at the north edge. Level 0 is the full-resolution grid; level `k + 1` keeps every
//! other sample of level `k`, so tile `(x, y)` of level `k + 1` covers tiles
//! `(2x..=2x+1, 2y..=2y+1)` of level `k` (those inside its grid).

use serde::{Deserialize, Serialize};
use std::fmt;

/// One tile of the pyramid: `level` 0 is full resolution, `x` counts columns from the west
/// edge, `y` rows from the north edge.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub struct TileId {
    #[serde(default)]
    pub level: u32,
    pub x: u32,
    pub y: u32,
}

impl TileId {
    /// A tile of level 0, the full-resolution grid.
    pub const fn new(x: u32, y: u32) -> Self {
        Self { level: 0, x, y }
    }

    /// A tile of any level.
    pub const fn at(level: u32, x: u32, y: u32) -> Self {
        Self { level, x, y }
    }

    /// The same column and row at another level (a re-tagging, not a parent or child).
    pub const fn with_level(self, level: u32) -> Self {
        Self { level, ..self }
    }

    /// Chebyshev distance in tiles: the belt index of `other` around `self`, both taken as
    /// tiles of one grid (their levels are not compared).
    pub fn belt_distance(self, other: TileId) -> u32 {
        self.x.abs_diff(other.x).max(self.y.abs_diff(other.y))
    }

    /// The tile of the next coarser level that covers this one.
    pub const fn parent(self) -> TileId {
        TileId::at(self.level + 1, self.x / 2, self.y / 2)
    }

    /// The (up to) four tiles of the next finer level this one covers, before clipping to
    /// that level's grid. `None` at level 0.
    pub fn children(self) -> Option<[TileId; 4]> {
        let level = self.level.checked_sub(1)?;
        let (x, y) = (self.x * 2, self.y * 2);
        Some([
            TileId::at(level, x, y),
            TileId::at(level, x + 1, y),
            TileId::at(level, x, y + 1),
            TileId::at(level, x + 1, y + 1),
        ])
    }
}

impl fmt::Display for TileId {
    /// `x/y` at level 0 (the grid users know), `level:x/y` above it.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.level == 0 {
            write!(f, "{}/{}", self.x, self.y)
        } else {
            write!(f, "L{}:{}/{}", self.level, self.x, self.y)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parents_and_children_are_inverse() {
        let tile = TileId::at(2, 5, 3);
        for child in tile.children().expect("level 2 has children") {
            assert_eq!(child.parent(), tile);
        }
        assert_eq!(TileId::new(4, 4).children(), None);
        assert_eq!(TileId::new(3, 2).to_string(), "3/2");
        assert_eq!(tile.to_string(), "L2:5/3");
    }
}
