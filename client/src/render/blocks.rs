//! MapBlocks (Brodersen 2005, section 5, "Texture handling"): a terrain texture larger than
//! the adapter's largest texture is cut into sub-textures each covering `n x m` tiles, small
//! enough to be bound; every visible tile is drawn with its block's texture, one block after
//! the other, so each block's texture is bound once per frame.
//!
//! Here the texture arrives per tile and level from the server; a block's texture is
//! assembled on the GPU by copying its resident tiles' textures (every mip) side by side, at
//! the finest level all of them hold, and assembled again when one of them changes. A tile
//! finds its part of the block texture through its uniforms (`TileUniform::uv`). This module
//! holds which tiles make a block, where each lies in the block's texture, and the blocks
//! assembled so far ([`Blocks`]); [`super::tiles`] assembles them on the GPU.
//!
//! A block is assembled only from a full rectangle of its tiles at one texture level, and
//! dropped as soon as any of its tiles changes texture or leaves: its texture never holds a
//! texel that is not a copy of a texture its tile holds now, so it costs at most as much as
//! those textures.

use std::collections::{HashMap, HashSet};
use terrain_shared::TileId;

/// Copies of a tile's GPU texture held while MapBlocks are on: its own, and its part of the
/// block texture (at most as fine, and no holes: see the module documentation). Memory
/// budgets charge a tile's GPU texture this many times.
pub const TEXTURE_COPIES: u64 = 2;

/// How the tile grid is cut into blocks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BlockLayout {
    /// Tiles per block, east and south: as many as fit under the texture limit at the
    /// finest texture level, and no more than the grid has.
    pub tiles: [u32; 2],
    /// The tile grid, columns and rows.
    pub grid: [u32; 2],
}

impl BlockLayout {
    /// Blocks for a `grid` of tiles whose finest texture is `finest_side` texels a side,
    /// under a texture side limit of `limit` texels. A block has at least one tile (a single
    /// tile's texture already keeps within the adapter's limit: its finer levels are left
    /// out).
    pub fn new(grid: [u32; 2], finest_side: u32, limit: u32) -> BlockLayout {
        let fit = (limit / finest_side.max(1)).max(1);
        BlockLayout {
            tiles: [fit.min(grid[0].max(1)), fit.min(grid[1].max(1))],
            grid,
        }
    }

    /// Blocks east and south.
    pub fn blocks(&self) -> [u32; 2] {
        [
            self.grid[0].div_ceil(self.tiles[0]),
            self.grid[1].div_ceil(self.tiles[1]),
        ]
    }

    /// The block holding `id`.
    pub fn block_of(&self, id: TileId) -> [u32; 2] {
        [id.x / self.tiles[0], id.y / self.tiles[1]]
    }

    /// The tiles of `block`, clipped to the grid.
    pub fn members(&self, block: [u32; 2]) -> impl Iterator<Item = TileId> + '_ {
        let x0 = block[0] * self.tiles[0];
        let y0 = block[1] * self.tiles[1];
        let x1 = (x0 + self.tiles[0]).min(self.grid[0]);
        let y1 = (y0 + self.tiles[1]).min(self.grid[1]);
        (y0..y1).flat_map(move |y| (x0..x1).map(move |x| TileId::new(x, y)))
    }
}

/// The rectangle of tiles a block's texture covers: the bounding box of its resident tiles
/// (a block at the edge of the paged square holds only part of its tiles), `[x0, y0]`
/// inclusive, `[x1, y1]` exclusive.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BlockRect {
    pub min: [u32; 2],
    pub max: [u32; 2],
}

impl BlockRect {
    /// The bounding box of `tiles` (`None` when there are none).
    pub fn around(tiles: impl IntoIterator<Item = TileId>) -> Option<BlockRect> {
        tiles.into_iter().fold(None, |rect, id| {
            let (min, max) = rect.map_or(([id.x, id.y], [id.x + 1, id.y + 1]), |r: BlockRect| {
                (
                    [r.min[0].min(id.x), r.min[1].min(id.y)],
                    [r.max[0].max(id.x + 1), r.max[1].max(id.y + 1)],
                )
            });
            Some(BlockRect { min, max })
        })
    }

    /// Tiles east and south.
    pub fn size(&self) -> [u32; 2] {
        [self.max[0] - self.min[0], self.max[1] - self.min[1]]
    }

    /// Texel where `id`'s part starts in a block texture of `side` texels a tile.
    pub fn texel_origin(&self, id: TileId, side: u32) -> [u32; 2] {
        [(id.x - self.min[0]) * side, (id.y - self.min[1]) * side]
    }

    /// `id`'s part of the block texture in texture coordinates: offset and scale, as the
    /// shader's `Tile::uv`.
    pub fn uv(&self, id: TileId) -> [f32; 4] {
        let [w, h] = self.size().map(|s| s as f32);
        [
            (id.x - self.min[0]) as f32 / w,
            (id.y - self.min[1]) as f32 / h,
            1.0 / w,
            1.0 / h,
        ]
    }
}

/// An assembled block texture.
#[derive(Debug)]
pub(super) struct Block {
    /// Its resident tiles and their texture versions when it was assembled.
    members: Vec<(TileId, u64)>,
    /// The tiles drawn with it: those whose texture is at the block's level (the others,
    /// still coarser, are drawn with their own until they catch up).
    holds: HashSet<TileId>,
    pub(super) rect: BlockRect,
    pub(super) group: wgpu::BindGroup,
    bytes: u64,
}

/// MapBlocks: the layout and the blocks assembled so far.
#[derive(Debug)]
pub(super) struct Blocks {
    pub(super) layout: BlockLayout,
    pub(super) assembled: HashMap<[u32; 2], Block>,
    /// Blocks whose tiles could not make one (holes), with the members' versions then: not
    /// tried again until one of them changes.
    unassembled: HashMap<[u32; 2], Vec<(TileId, u64)>>,
}

impl Blocks {
    pub(super) fn new(layout: BlockLayout) -> Blocks {
        Blocks {
            layout,
            assembled: HashMap::new(),
            unassembled: HashMap::new(),
        }
    }

    /// GPU bytes of the assembled block textures.
    pub(super) fn bytes(&self) -> u64 {
        self.assembled.values().map(|b| b.bytes).sum()
    }

    /// Drops the block of `id` (its texture changed, or it left).
    pub(super) fn forget(&mut self, id: TileId) {
        let key = self.layout.block_of(id);
        self.assembled.remove(&key);
        self.unassembled.remove(&key);
    }

    /// Whether block `key` was made (or found unmakeable) from exactly `members`.
    pub(super) fn is_current(&self, key: [u32; 2], members: &[(TileId, u64)]) -> bool {
        self.assembled
            .get(&key)
            .is_some_and(|b| b.members == members)
            || self.unassembled.get(&key).is_some_and(|m| m == members)
    }

    /// Whether block `key` is assembled and draws `id`.
    pub(super) fn holds(&self, key: [u32; 2], id: TileId) -> bool {
        self.assembled
            .get(&key)
            .is_some_and(|b| b.holds.contains(&id))
    }

    pub(super) fn remember_unassembled(&mut self, key: [u32; 2], members: Vec<(TileId, u64)>) {
        self.unassembled.insert(key, members);
    }

    pub(super) fn insert(
        &mut self,
        key: [u32; 2],
        members: Vec<(TileId, u64)>,
        holds: Vec<TileId>,
        rect: BlockRect,
        group: wgpu::BindGroup,
        bytes: u64,
    ) {
        self.unassembled.remove(&key);
        self.assembled.insert(
            key,
            Block {
                members,
                holds: holds.into_iter().collect(),
                rect,
                group,
                bytes,
            },
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn blocks_fit_the_limit_and_cover_every_tile_once() {
        let layout = BlockLayout::new([7, 6], 128, 300);
        assert_eq!(layout.tiles, [2, 2], "two 128-texel tiles fit in 300");
        assert_eq!(layout.blocks(), [4, 3]);
        let mut seen = std::collections::HashSet::new();
        for by in 0..3 {
            for bx in 0..4 {
                for id in layout.members([bx, by]) {
                    assert_eq!(layout.block_of(id), [bx, by]);
                    assert!(seen.insert(id), "{id} in two blocks");
                }
            }
        }
        assert_eq!(seen.len(), 42);
        // A limit above the whole texture makes one block; one below a tile, one tile each.
        assert_eq!(BlockLayout::new([7, 6], 128, 16384).blocks(), [1, 1]);
        assert_eq!(BlockLayout::new([7, 6], 128, 64).tiles, [1, 1]);
    }

    #[test]
    fn a_tile_finds_its_part_of_the_block_texture() {
        let rect = BlockRect::around([TileId::new(4, 2), TileId::new(5, 3), TileId::new(5, 2)])
            .expect("tiles");
        assert_eq!(
            rect,
            BlockRect {
                min: [4, 2],
                max: [6, 4]
            }
        );
        assert_eq!(rect.texel_origin(TileId::new(5, 3), 64), [64, 64]);
        assert_eq!(rect.uv(TileId::new(5, 2)), [0.5, 0.0, 0.5, 0.5]);
        assert_eq!(BlockRect::around(std::iter::empty()), None);
    }
}
