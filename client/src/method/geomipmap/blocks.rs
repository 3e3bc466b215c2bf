//! A tile cut into GeoMipMaps of `(2^k + 1)^2` samples, each with its own level, as
//! Brodersen's paper draws them: "the terrain is subdivided into a number of smaller
//! patches, called GeoMipMaps, of size `(2^n+1)x(2^n+1)` samples (typically either 17x17 or
//! 33x33)". Our tiles play the paper's MapBlocks (the unit of paging and texture); each
//! holds `(tile cells / 8)^2` GeoMipMaps of 9x9 samples ([`BLOCK_CELLS`]), or one when a
//! tile has fewer cells.
//!
//! The paper found 17x17 the best balance of draw calls against triangles on its hardware.
//! Here the size is chosen against the triangle oracle (`bench accuracy`): the smaller the
//! block, the nearer each block's level comes to what its own samples need (the block-grids
//! table of docs/evaluation.md), and with 9x9 blocks GeoMipMaps stay within twice the
//! oracle on the evaluation's flights (`accuracy::geomipmaps_keep_every_pixel_*`). A
//! block's errors cost [`BlockErrors::bytes_for`] bytes, counted with the tile.
//!
//! A block's index sets are those of [`super::stitching`] for a tile of the block's size,
//! its sample indices rewritten to the tile's row stride ([`Blocks::to_tile`]): the same set
//! draws every block of every tile, placed by the draw's base vertex
//! ([`Blocks::base_vertex`]), which the vertex shader's `vertex_index` includes.

use super::stitching::{self, RESTART};
use crate::lod::needed;

/// Cells a side of one GeoMipMap (9x9 samples), or the whole tile if smaller.
pub const BLOCK_CELLS: u32 = 8;

/// How tiles of `n` samples a side are cut into blocks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Blocks {
    /// Samples a side of a tile.
    pub n: u32,
    /// Cells a side of a block.
    pub cells: u32,
    /// Blocks a side of a tile.
    pub per_side: u32,
}

impl Blocks {
    /// Blocks of [`BLOCK_CELLS`] cells, or one block a tile when it has fewer (tile sizes are
    /// `2^m + 1`, so the blocks tile it exactly).
    pub fn new(n: u32) -> Blocks {
        let cells = (n - 1).min(BLOCK_CELLS);
        Blocks {
            n,
            cells,
            per_side: (n - 1) / cells,
        }
    }

    /// Samples a side of a block.
    pub fn size(&self) -> u32 {
        self.cells + 1
    }

    /// Blocks in a tile.
    pub fn count(&self) -> usize {
        (self.per_side * self.per_side) as usize
    }

    /// Levels of a block (`0..`, the last one cell).
    pub fn levels(&self) -> u32 {
        stitching::level_count(self.size())
    }

    /// Block `b` (row-major) as (column, row) of blocks.
    pub fn at(&self, b: usize) -> (u32, u32) {
        (b as u32 % self.per_side, b as u32 / self.per_side)
    }

    /// The tile's index of block (`bx`, `by`)'s north-west sample: the base vertex its sets
    /// are drawn with.
    pub fn base_vertex(&self, bx: u32, by: u32) -> u32 {
        by * self.cells * self.n + bx * self.cells
    }

    /// A block-local index (sample `y * size + x`, or the skirt foot `size^2 + i` of sample
    /// `i`, or [`RESTART`]) as the index of the same vertex of the tile's north-west block:
    /// the tile's own numbering (samples `y * n + x`, feet `n^2 + i`).
    pub fn to_tile(&self, local: u32) -> u32 {
        let m = self.size();
        let sample = |i: u32| (i / m) * self.n + i % m;
        if local == RESTART {
            RESTART
        } else if local < m * m {
            sample(local)
        } else {
            terrain_shaders::skirt_base(self.n) + sample(local - m * m)
        }
    }
}

/// What a tile's blocks need to choose their levels: per block, the suffix minima of its
/// levels' errors ([`stitching::level_errors`] of the block's samples, metres) and the
/// range of its heights (its box's bottom and top).
#[derive(Debug, Clone, PartialEq)]
pub struct BlockErrors {
    levels: usize,
    minima: Vec<f32>,
    range_m: Vec<[f32; 2]>,
}

impl BlockErrors {
    /// The errors and ranges of the blocks of a tile whose heights (metres, row-major) are
    /// `samples`.
    pub fn new(samples: &[f32], blocks: Blocks) -> BlockErrors {
        let (m, n) = (blocks.size() as usize, blocks.n as usize);
        let levels = blocks.levels() as usize;
        let mut minima = Vec::with_capacity(blocks.count() * levels);
        let mut range_m = Vec::with_capacity(blocks.count());
        let mut block = vec![0.0f32; m * m];
        for b in 0..blocks.count() {
            let (bx, by) = blocks.at(b);
            let base = blocks.base_vertex(bx, by) as usize;
            for (y, row) in block.chunks_exact_mut(m).enumerate() {
                row.copy_from_slice(&samples[base + y * n..base + y * n + m]);
            }
            let (lo, hi) = block
                .iter()
                .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &h| {
                    (lo.min(h), hi.max(h))
                });
            range_m.push([lo, hi]);
            minima.extend(needed::suffix_minima(&stitching::level_errors(
                &block, m as u32,
            )));
        }
        BlockErrors {
            levels,
            minima,
            range_m,
        }
    }

    /// Suffix minima of block `b`'s level errors, metres.
    pub fn minima(&self, b: usize) -> &[f32] {
        &self.minima[b * self.levels..(b + 1) * self.levels]
    }

    /// Lowest and highest height of block `b`, metres.
    pub fn range_m(&self, b: usize) -> [f32; 2] {
        self.range_m[b]
    }

    /// Bytes held.
    pub fn bytes(&self) -> u64 {
        Self::bytes_for(self.range_m.len(), self.levels)
    }

    /// Bytes held for a tile of `blocks`.
    pub fn bytes_for(count: usize, levels: usize) -> u64 {
        4 * (count * levels + 2 * count) as u64
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn blocks_of_nine_samples_tile_a_tile_and_map_to_its_stride() {
        let b = Blocks::new(129);
        assert_eq!(
            (b.cells, b.per_side, b.count(), b.levels()),
            (8, 16, 256, 4)
        );
        assert_eq!(Blocks::new(9).per_side, 1);
        assert_eq!(Blocks::new(5).cells, 4);
        assert_eq!(b.base_vertex(1, 2), 2 * 8 * 129 + 8);
        // Sample (3, 2) of a block, and its skirt foot.
        assert_eq!(b.to_tile(2 * 9 + 3), 2 * 129 + 3);
        assert_eq!(b.to_tile(9 * 9 + 2 * 9 + 3), 129 * 129 + 2 * 129 + 3);
        assert_eq!(b.to_tile(RESTART), RESTART);
    }

    #[test]
    fn each_block_is_measured_on_its_own_samples() {
        // A tile flat but for one bump in block (1, 0): only that block has errors.
        let n = 17;
        let mut samples = vec![0.0f32; (n * n) as usize];
        samples[(5 * n + 8 + 5) as usize] = 7.0;
        let errors = BlockErrors::new(&samples, Blocks::new(n));
        assert_eq!(errors.minima(1)[0], 0.0);
        assert!(errors.minima(1)[1] >= 7.0, "{:?}", errors.minima(1));
        for b in [0, 2, 3] {
            assert!(errors.minima(b).iter().all(|&e| e == 0.0), "block {b}");
            assert_eq!(errors.range_m(b), [0.0, 0.0]);
        }
        assert_eq!(errors.range_m(1), [0.0, 7.0]);
        assert_eq!(errors.bytes(), 4 * (4 * 4 + 8));
    }
}
