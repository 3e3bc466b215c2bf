//! The texture budget: how fine each tile's texture goes (the strip-mask paper's
//! progressive texture transfer, section 4).
//!
//! A tile arrives with its coarsest texture level; finer levels are fetched one at a time,
//! coarse to fine, while the tile's share of the texture budget pays for them. The budget is
//! the memory the pager leaves free: its limit, less what the resident tiles hold at their
//! coarsest level, less what the tiles still coming will hold. It is shared greedily by
//! importance, like the triangle budget ([`crate::lod::budget::share`]): each tile is offered
//! `pool * importance / remaining importance`, takes the finest level whose extra cost fits,
//! and leaves the rest to the tiles after it. A tile over its share drops back at once, so
//! the pager's limit holds whatever textures arrive.

/// One tile competing for the texture budget.
#[derive(Debug, Clone, PartialEq)]
pub struct TextureCandidate<'a> {
    /// Its visual importance (visible tiles); 0 for tiles out of view, which are served last.
    pub importance: f64,
    /// Extra bytes of holding each level, index = level: 0 for the coarsest (paid by the
    /// pager's accounting), then non-decreasing.
    pub extra_cost: &'a [u64],
}

/// The candidates' indices, most important first (equal importances in the candidates'
/// order): the order the budget is shared in, and its reverse the order levels are dropped.
pub fn most_important_first(candidates: &[TextureCandidate<'_>]) -> Vec<usize> {
    let mut order: Vec<usize> = (0..candidates.len()).collect();
    order.sort_by(|&a, &b| {
        candidates[b]
            .importance
            .total_cmp(&candidates[a].importance)
            .then(a.cmp(&b))
    });
    order
}

/// The finest level each candidate may hold, in the candidates' order.
pub fn share_texture_budget(candidates: &[TextureCandidate<'_>], budget: u64) -> Vec<u32> {
    let order = most_important_first(candidates);
    let mut remaining: f64 = candidates.iter().map(|c| c.importance.max(0.0)).sum();
    // Counted, not read off `remaining`: a sum of importances less each one in turn
    // rounds to a few ulps above or below 0, and whether the tiles out of view get a share
    // must not flip with it from frame to frame.
    let visible = candidates.iter().filter(|c| c.importance > 0.0).count();
    let mut pool = budget;
    let mut levels = vec![0u32; candidates.len()];
    for (served, &i) in order.iter().enumerate() {
        let candidate = &candidates[i];
        let importance = candidate.importance.max(0.0);
        let offer = if served + 1 == visible {
            // The last visible tile may take all that is left.
            pool
        } else if served < visible {
            ((pool as f64) * (importance / remaining).min(1.0)).floor() as u64
        } else {
            // Only tiles out of view are left: they share what the visible ones left evenly.
            pool / (order.len() - served) as u64
        };
        let level = candidate
            .extra_cost
            .iter()
            .rposition(|&cost| cost <= offer)
            .unwrap_or(0);
        let cost = candidate.extra_cost.get(level).copied().unwrap_or(0);
        pool = pool.saturating_sub(cost);
        remaining = (remaining - importance).max(0.0);
        levels[i] = level as u32;
    }
    levels
}

/// Extra bytes of holding each texture level of a tile (index = level; `texture` its
/// tile blob's table) beyond the
/// coarsest: the encoded levels kept on the CPU plus their RGBA mips on the GPU, `gpu_copies`
/// times (2 with MapBlocks, whose block textures copy the tiles').
pub fn extra_costs(
    manifest: &terrain_shared::Manifest,
    texture: &[terrain_shared::Blob],
    gpu_copies: u64,
) -> Vec<u64> {
    let mut cost = 0u64;
    (0..texture.len())
        .map(|level| {
            if level > 0 {
                let side = u64::from(manifest.texture.level_size(level as u32));
                cost += texture[level].bytes + gpu_copies * side * side * 4;
            }
            cost
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn candidate(importance: f64) -> TextureCandidate<'static> {
        TextureCandidate {
            importance,
            extra_cost: &[0, 100, 300, 1000],
        }
    }

    #[test]
    fn the_budget_goes_to_the_most_important_tiles_and_is_never_exceeded() {
        let tiles = [candidate(0.1), candidate(0.6), candidate(0.3)];
        // 1000 bytes: tile 1 is offered 600 (takes 300), the 700 left go 0.3/0.4 to tile 2
        // (525: 300), then tile 0 gets the 400 left (300).
        assert_eq!(share_texture_budget(&tiles, 1000), vec![2, 2, 2]);
        assert_eq!(share_texture_budget(&tiles, 400), vec![1, 1, 1]);
        assert_eq!(share_texture_budget(&tiles, 0), vec![0, 0, 0]);
        for budget in (0..3000).step_by(37) {
            let levels = share_texture_budget(&tiles, budget);
            let spent: u64 = levels
                .iter()
                .zip(&tiles)
                .map(|(&l, t)| t.extra_cost[l as usize])
                .sum();
            assert!(spent <= budget, "budget {budget}: spent {spent}");
        }
    }

    #[test]
    fn tiles_out_of_view_share_what_visible_tiles_leave() {
        let tiles = [candidate(0.0), candidate(1.0), candidate(0.0)];
        assert_eq!(share_texture_budget(&tiles, 1000 + 600), vec![2, 3, 2]);
        assert_eq!(share_texture_budget(&tiles, 1000), vec![0, 3, 0]);
    }

    #[test]
    fn rounding_in_the_importances_never_decides_the_tiles_out_of_view() {
        // 0.3 + 0.2 + 0.1, less each in turn, leaves 2.8e-17 rather than 0; the tiles out of
        // view must get their share all the same.
        let left = [0.3, 0.2, 0.1]
            .iter()
            .fold(0.1 + 0.2 + 0.3, |r: f64, i| r - i);
        assert!(left > 0.0, "{left}");
        let tiles = [
            candidate(0.0),
            candidate(0.1),
            candidate(0.2),
            candidate(0.3),
            candidate(0.0),
        ];
        assert_eq!(share_texture_budget(&tiles, 5000), vec![3, 3, 3, 3, 3]);
        // The same share whatever the visible importances add up to.
        let scaled: Vec<_> = [0.0, 0.1, 0.2, 0.3, 0.0]
            .iter()
            .map(|&i| candidate(i * 0.7))
            .collect();
        assert_eq!(share_texture_budget(&scaled, 5000), vec![3, 3, 3, 3, 3]);
    }
}
