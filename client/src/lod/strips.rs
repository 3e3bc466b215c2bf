//! The mask set: one triangle strip per mask level, shared by every tile of a terrain, and
//! the choice of the finest mask that fits a triangle budget.
//!
//! Strip-mask paper, section 5.1: all tiles have the same `n x n` samples, so one index
//! buffer per mask level serves every tile's vertex buffer, and masks are built lazily, the
//! first time a level is drawn. Which samples a level keeps, and the diagonal each cell is
//! split along, are `terrain_shared::mask`'s: the builder measured each level's error with
//! that triangulation, so the strips here reproduce it exactly.
//!
//! A strip indexes the tile's vertices row-major (`y * tile_size + x`, y south). It walks
//! each pair of kept rows `r0 < r1` west to east, north vertex first: `(c, r0), (c, r1)` for
//! every kept column `c`. Each cell then becomes the triangles `(c0,r0) (c0,r1) (c1,r0)` and
//! `(c0,r1) (c1,r0) (c1,r1)`, split along the diagonal from `(c0, r1)` to `(c1, r0)`, the
//! convention of `terrain_shared::mask`. Row pairs are joined by repeating the last index of
//! one and the first of the next, which adds [`DEGENERATE_TRIANGLES_PER_JOIN`] zero-area
//! triangles per join; every row pair has an even number of vertices and every join adds
//! two, so all drawn triangles keep the winding of the first one.
//!
//! The module leaves uploading strips, and the front-face convention, to the renderer.

use std::sync::OnceLock;
use terrain_shared::mask;

/// Zero-area triangles a join between two row pairs adds: the strip `.. a B B C C d ..`
/// yields `aBB`, `BBC`, `BCC` and `CCd`, all with a repeated index, which GPUs discard.
pub const DEGENERATE_TRIANGLES_PER_JOIN: u32 = 4;

/// The strips of every mask level of one tile size, built on first use and then shared.
#[derive(Debug)]
pub struct MaskSet {
    tile_size: u32,
    /// One strip per level, built by [`MaskSet::strip`] the first time it is asked for.
    strips: Vec<OnceLock<Vec<u32>>>,
    /// Drawn triangles per level, non-increasing with the level.
    triangles: Vec<u32>,
    /// Distinct triangle counts in increasing order, each with the smallest level drawing
    /// that many: what [`MaskSet::select`] searches.
    selectable: Vec<(u32, u32)>,
}

impl MaskSet {
    /// The mask set of tiles of `tile_size` samples per side; no strip is built yet.
    ///
    /// Panics if `tile_size < 2`: such a tile has no cell and no mask (a caller bug; the
    /// manifest's tiles are `2^n + 1` samples, at least 3).
    pub fn new(tile_size: u32) -> MaskSet {
        assert!(tile_size >= 2, "a tile needs at least 2 samples per side");
        let levels = mask::level_count(tile_size);
        let triangles: Vec<u32> = (0..levels)
            .map(|level| mask::triangle_count(tile_size, level))
            .collect();
        // Counts never grow with the level, so walking from the coarsest level down and
        // replacing the entry of an equal count keeps the smallest level for each count:
        // the paper's figure 4 (levels 2 and 3 of a 6x6 tile both draw 8 triangles; level 2
        // is the one chosen for a budget, level 3 only serves transitions).
        let mut selectable: Vec<(u32, u32)> = Vec::new();
        for level in (0..levels).rev() {
            let count = triangles[level as usize];
            match selectable.last_mut() {
                Some(last) if last.0 == count => last.1 = level,
                _ => selectable.push((count, level)),
            }
        }
        MaskSet {
            tile_size,
            strips: (0..levels).map(|_| OnceLock::new()).collect(),
            triangles,
            selectable,
        }
    }

    /// Samples per tile side.
    pub fn tile_size(&self) -> u32 {
        self.tile_size
    }

    /// Number of mask levels, `tile_size - 1`; level 0 is the full tile.
    pub fn level_count(&self) -> u32 {
        self.triangles.len() as u32
    }

    /// The coarsest level: two triangles over the whole tile.
    pub fn coarsest_level(&self) -> u32 {
        self.level_count() - 1
    }

    /// The strip of `level`, built on the first call for that level (from any thread).
    ///
    /// Panics if `level >= level_count()`.
    pub fn strip(&self, level: u32) -> &[u32] {
        self.strips[level as usize].get_or_init(|| build_strip(self.tile_size, level))
    }

    /// The strip of `level`, built now and not kept (for a caller that uploads it and needs
    /// no CPU copy).
    ///
    /// Panics if `level >= level_count()`.
    pub fn build(&self, level: u32) -> Vec<u32> {
        assert!(level < self.level_count(), "no mask level {level}");
        build_strip(self.tile_size, level)
    }

    /// Triangles `level` draws, strip joins not counted: `terrain_shared::mask::triangle_count`.
    pub fn triangle_count(&self, level: u32) -> u32 {
        self.triangles[level as usize]
    }

    /// Indices in the strip of `level`, joins included, without building it.
    pub fn strip_len(&self, level: u32) -> usize {
        let kept = mask::kept_indices(self.tile_size, level).len();
        let pairs = kept - 1;
        pairs * 2 * kept + 2 * self.join_count(level) as usize
    }

    /// Bytes held: the strips built so far and the tables.
    pub fn bytes(&self) -> u64 {
        let strips: usize = self
            .strips
            .iter()
            .filter_map(|s| s.get().map(|s| 4 * s.len()))
            .sum();
        (strips + 4 * self.triangles.len() + 8 * self.selectable.len()) as u64
    }

    /// Joins between row pairs in the strip of `level`: each adds
    /// [`DEGENERATE_TRIANGLES_PER_JOIN`] zero-area triangles.
    pub fn join_count(&self, level: u32) -> u32 {
        mask::kept_indices(self.tile_size, level).len() as u32 - 2
    }

    /// The finest level drawing at most `budget` triangles; among levels drawing the same
    /// count, the smallest index (the paper's figure 4). If even the coarsest level does not
    /// fit, the coarsest level: a visible tile always draws something, and the caller
    /// (`budget::share`) accounts for the overspend. O(log n) over the distinct counts.
    pub fn select(&self, budget: u32) -> u32 {
        let fitting = self
            .selectable
            .partition_point(|&(count, _)| count <= budget);
        match fitting.checked_sub(1) {
            Some(index) => self.selectable[index].1,
            None => self.coarsest_level(),
        }
    }
}

/// The strip of mask `level` over a `tile_size` tile, as described in the module docs.
fn build_strip(tile_size: u32, level: u32) -> Vec<u32> {
    let kept = mask::kept_indices(tile_size, level);
    let mut strip = Vec::with_capacity((kept.len() - 1) * (2 * kept.len() + 2));
    for (pair, rows) in kept.windows(2).enumerate() {
        let (north, south) = (rows[0] * tile_size, rows[1] * tile_size);
        if pair > 0 {
            // Join: repeat the previous pair's last index and this pair's first.
            let last = *strip.last().expect("a previous row pair was written");
            strip.push(last);
            strip.push(north + kept[0]);
        }
        for &column in &kept {
            strip.push(north + column);
            strip.push(south + column);
        }
    }
    strip
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::BTreeSet;

    /// What one strip looks like once walked triangle by triangle.
    #[derive(Debug, PartialEq)]
    struct Walk {
        drawn: u32,
        zero_area: u32,
        /// Twice the summed area of the drawn triangles, in index space.
        doubled_area: i64,
        /// Signs of the drawn triangles' areas after undoing the strip's alternation.
        windings: BTreeSet<i64>,
    }

    fn walk(tile_size: u32, strip: &[u32]) -> Walk {
        let at = |i: u32| ((i % tile_size) as i64, (i / tile_size) as i64);
        let mut walk = Walk {
            drawn: 0,
            zero_area: 0,
            doubled_area: 0,
            windings: BTreeSet::new(),
        };
        for (k, t) in strip.windows(3).enumerate() {
            let ((x0, y0), (x1, y1), (x2, y2)) = (at(t[0]), at(t[1]), at(t[2]));
            // Shoelace formula: twice the signed area.
            let doubled = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0);
            if doubled == 0 {
                walk.zero_area += 1;
            } else {
                walk.drawn += 1;
                walk.doubled_area += doubled.abs();
                let alternation = if k % 2 == 0 { 1 } else { -1 };
                walk.windings.insert(doubled.signum() * alternation);
            }
        }
        walk
    }

    /// Every structural property of every level of `tile_size`.
    fn check(tile_size: u32) {
        let masks = MaskSet::new(tile_size);
        let n = tile_size as i64;
        assert_eq!(masks.level_count(), mask::level_count(tile_size));
        for level in 0..masks.level_count() {
            let strip = masks.strip(level);
            let context = format!("tile {tile_size} level {level}");
            assert_eq!(strip.len(), masks.strip_len(level), "{context}");
            let walk = walk(tile_size, strip);
            assert_eq!(walk.drawn, masks.triangle_count(level), "{context}");
            assert_eq!(
                walk.drawn,
                mask::triangle_count(tile_size, level),
                "{context}"
            );
            assert_eq!(walk.doubled_area, 2 * (n - 1) * (n - 1), "{context}");
            assert_eq!(
                walk.zero_area,
                DEGENERATE_TRIANGLES_PER_JOIN * masks.join_count(level),
                "{context}"
            );
            assert_eq!(walk.windings.len(), 1, "{context}: mixed windings");

            // Borders: the samples used on each edge are exactly the kept ones, so a
            // neighbour at the same level meets this tile vertex for vertex.
            let kept: BTreeSet<u32> = mask::kept_indices(tile_size, level).into_iter().collect();
            let used: BTreeSet<u32> = strip.iter().copied().collect();
            let last = tile_size - 1;
            // (edge, index of its first sample, step between its samples)
            let edges = [
                ("north", 0, 1),
                ("south", last * tile_size, 1),
                ("west", 0, tile_size),
                ("east", last, tile_size),
            ];
            for (edge, first, step) in edges {
                let on_edge: BTreeSet<u32> = (0..tile_size)
                    .filter(|&k| used.contains(&(first + k * step)))
                    .collect();
                assert_eq!(on_edge, kept, "{context}: {edge} edge");
            }
        }
    }

    #[test]
    fn every_mask_covers_the_tile_meets_its_neighbours_and_degenerates_only_at_joins() {
        for tile_size in [2, 3, 5, 6, 9, 17, 33] {
            check(tile_size);
        }
    }

    #[test]
    fn every_mask_of_a_129_tile_is_sound() {
        check(129);
    }

    #[test]
    fn triangle_counts_are_the_shared_ones() {
        let six = MaskSet::new(6);
        let counts: Vec<u32> = (0..5).map(|l| six.triangle_count(l)).collect();
        assert_eq!(counts, vec![50, 18, 8, 8, 2]);
        let full = MaskSet::new(129);
        assert_eq!(full.triangle_count(0), 32768);
        assert_eq!(full.triangle_count(full.coarsest_level()), 2);
    }

    #[test]
    fn the_first_cell_is_split_from_south_west_to_north_east() {
        // A 3x3 tile at level 0: the first triangles are (0,0) (0,1) (1,0) and
        // (0,1) (1,0) (1,1), sharing the diagonal (0,1)-(1,0).
        assert_eq!(&MaskSet::new(3).strip(0)[..4], &[0, 3, 1, 4]);
        // Two row pairs joined by repeating 5 (end of the first) and 3 (start of the second).
        assert_eq!(
            MaskSet::new(3).strip(0),
            &[0, 3, 1, 4, 2, 5, 5, 3, 3, 6, 4, 7, 5, 8]
        );
    }

    #[test]
    fn selection_picks_the_finest_mask_that_fits_for_every_budget() {
        for tile_size in [6, 17, 33] {
            let masks = MaskSet::new(tile_size);
            for budget in 0..=masks.triangle_count(0) + 3 {
                let level = masks.select(budget);
                let expected = (0..masks.level_count())
                    .find(|&l| masks.triangle_count(l) <= budget)
                    .unwrap_or(masks.coarsest_level());
                assert_eq!(level, expected, "tile {tile_size} budget {budget}");
            }
        }
    }

    #[test]
    fn equal_counts_select_the_smaller_level_as_in_figure_4() {
        let masks = MaskSet::new(6);
        for budget in 8..=17 {
            assert_eq!(masks.select(budget), 2, "budget {budget}");
        }
        assert_eq!(
            masks.select(1),
            4,
            "too small a budget still draws the coarsest mask"
        );
    }

    #[test]
    fn strips_are_built_once_and_shared() {
        let masks = MaskSet::new(9);
        let first = masks.strip(2).as_ptr();
        assert_eq!(masks.strip(2).as_ptr(), first);
    }
}
