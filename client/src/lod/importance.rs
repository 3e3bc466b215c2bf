//! Visual importance: the share of the frame's detail each visible tile deserves.
//!
//! Strip-mask paper, section 5.2 (Algorithm 2, equation 1): near tiles and high or rugged
//! tiles matter more than far and flat ones. Each tile's importance is a weighted sum of a
//! distance term and a height term, `alpha` and `beta = 1 - alpha`, and the importances of
//! the visible tiles sum to 1, so that [`crate::lod::budget::share`] can hand each tile
//! `importance * budget` triangles.
//!
//! **Deviation from equation (1).** As printed it divides the distance term
//! `max_dist - dist_t` by `sum_t dist_t`, which does not sum to 1 over the tiles, although
//! the paper says the importances are normalised. Here each term is normalised by its own
//! sum: `(max_dist - dist_t) / sum_t (max_dist - dist_t)` and `h_t / sum_t h_t`, so each
//! sums to 1 and so does their weighted sum. When a term's sum is 0 (one tile, all tiles
//! equidistant, all tiles flat) it cannot rank the tiles and is spread evenly, `1 / n`
//! each, so the importances still sum to 1.
//!
//! The module leaves culling (which tiles are visible) and measuring distances to the
//! caller, and turning importances into triangles to [`crate::lod::budget`].

/// Weight of the distance term; the height term gets `1 - alpha`. The paper's trade-off,
/// "alpha = beta = 0.5", keeps the horizon's mountains while detailing near tiles.
pub const DEFAULT_ALPHA: f64 = 0.5;

/// What the importance needs to know of one visible tile.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TileView {
    /// Distance from the viewpoint to the tile's centre, metres.
    pub distance_m: f64,
    /// Height of the tile's bounding box (highest minus lowest sample), metres.
    pub bbox_height_m: f64,
    /// Roughness of the tile as the manifest tabulates it, metres.
    pub roughness_m: f64,
}

/// Which height a tile's height term uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum HeightMeasure {
    /// The bounding box's height, as in the paper.
    #[default]
    #[value(name = "bbox")]
    BoundingBox,
    /// Roughness: the paper's suggested alternative (a ruggedness index), which does not
    /// reward a smooth but steep slope.
    Roughness,
}

/// Importance of each tile of `tiles` (visible tiles only), in the same order, summing to 1
/// (an empty slice gives an empty vector). Negative heights count as 0.
///
/// Panics if `alpha` is outside `[0, 1]` (a caller bug).
pub fn importance(tiles: &[TileView], alpha: f64, height: HeightMeasure) -> Vec<f64> {
    let mut out = Vec::with_capacity(tiles.len());
    importance_into(tiles, alpha, height, &mut out);
    out
}

/// [`importance`] into a vector the caller reuses from frame to frame (cleared first).
pub fn importance_into(tiles: &[TileView], alpha: f64, height: HeightMeasure, out: &mut Vec<f64>) {
    assert!(
        (0.0..=1.0).contains(&alpha),
        "alpha must lie in [0, 1], got {alpha}"
    );
    out.clear();
    if tiles.is_empty() {
        return;
    }
    let beta = 1.0 - alpha;
    let height_of = |tile: &TileView| {
        let h = match height {
            HeightMeasure::BoundingBox => tile.bbox_height_m,
            HeightMeasure::Roughness => tile.roughness_m,
        };
        h.max(0.0)
    };
    let (mut max_distance, mut sum_height) = (f64::MIN, 0.0);
    for tile in tiles {
        max_distance = max_distance.max(tile.distance_m);
        sum_height += height_of(tile);
    }
    // Summed after the maximum is known, rather than as n * max - sum(dist), so that
    // equidistant tiles give exactly 0 and not a rounding residue.
    let sum_closeness: f64 = tiles.iter().map(|t| max_distance - t.distance_m).sum();
    let even = 1.0 / tiles.len() as f64;
    out.extend(tiles.iter().map(|tile| {
        let distance_term = if sum_closeness > 0.0 {
            (max_distance - tile.distance_m) / sum_closeness
        } else {
            even
        };
        let height_term = if sum_height > 0.0 {
            height_of(tile) / sum_height
        } else {
            even
        };
        alpha * distance_term + beta * height_term
    }));
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn tile(distance_m: f64, bbox_height_m: f64, roughness_m: f64) -> TileView {
        TileView {
            distance_m,
            bbox_height_m,
            roughness_m,
        }
    }

    fn check(tiles: &[TileView], alpha: f64, height: HeightMeasure, expect: &[f64]) {
        let got = importance(tiles, alpha, height);
        assert_eq!(got.len(), expect.len());
        for (i, (g, e)) in got.iter().zip(expect).enumerate() {
            assert!(
                (g - e).abs() < 1e-12,
                "tile {i}: got {got:?}, expected {expect:?}"
            );
        }
    }

    #[test]
    fn nearer_tiles_rank_higher_at_equal_height() {
        let tiles = [
            tile(100.0, 50.0, 1.0),
            tile(300.0, 50.0, 1.0),
            tile(500.0, 50.0, 1.0),
        ];
        // Closeness 400, 200, 0 of 600; heights even.
        let third = 1.0 / 3.0;
        check(
            &tiles,
            0.5,
            HeightMeasure::BoundingBox,
            &[
                0.5 * 4.0 / 6.0 + 0.5 * third,
                0.5 * 2.0 / 6.0 + 0.5 * third,
                0.5 * third,
            ],
        );
    }

    #[test]
    fn rougher_tiles_rank_higher_at_equal_distance() {
        let tiles = [tile(200.0, 90.0, 1.0), tile(200.0, 10.0, 3.0)];
        // Equidistant: the distance term is spread evenly.
        check(
            &tiles,
            0.5,
            HeightMeasure::Roughness,
            &[0.25 + 0.125, 0.25 + 0.375],
        );
        check(
            &tiles,
            0.5,
            HeightMeasure::BoundingBox,
            &[0.25 + 0.45, 0.25 + 0.05],
        );
    }

    #[test]
    fn alpha_one_is_distance_only_and_zero_is_height_only() {
        let tiles = [tile(0.0, 1.0, 0.0), tile(10.0, 3.0, 0.0)];
        check(&tiles, 1.0, HeightMeasure::BoundingBox, &[1.0, 0.0]);
        check(&tiles, 0.0, HeightMeasure::BoundingBox, &[0.25, 0.75]);
    }

    #[test]
    fn degenerate_sets_spread_evenly() {
        check(&[], 0.5, HeightMeasure::BoundingBox, &[]);
        check(
            &[tile(7.0, 0.0, 0.0)],
            0.5,
            HeightMeasure::BoundingBox,
            &[1.0],
        );
        let flat_and_equidistant = [tile(5.0, 0.0, 0.0); 4];
        check(
            &flat_and_equidistant,
            0.3,
            HeightMeasure::Roughness,
            &[0.25; 4],
        );
    }

    proptest! {
        #[test]
        fn importances_sum_to_one(
            tiles in prop::collection::vec((0.0..1e5f64, 0.0..3e3f64, 0.0..1e2f64), 1..300),
            alpha in 0.0..=1.0f64,
            roughness in any::<bool>(),
        ) {
            let tiles: Vec<TileView> = tiles.into_iter().map(|(d, h, r)| tile(d, h, r)).collect();
            let height = if roughness { HeightMeasure::Roughness } else { HeightMeasure::BoundingBox };
            let importances = importance(&tiles, alpha, height);
            prop_assert_eq!(importances.len(), tiles.len());
            prop_assert!(importances.iter().all(|&i| (0.0..=1.0 + 1e-12).contains(&i)));
            let sum: f64 = importances.iter().sum();
            prop_assert!((sum - 1.0).abs() < 1e-9, "sum {}", sum);
        }
    }
}
