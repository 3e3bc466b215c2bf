//! The fewest triangles a frame needs: per tile, the coarsest strip mask whose vertical
//! error, projected to the screen, stays within a threshold in pixels. What a frame draws,
//! set against this, says whether it models more than the scene needs (a flat tile needs
//! two triangles whatever the budget).
//!
//! The projection is the usual screen-space error bound (e.g. Yusov and Turlapov's quadtree
//! patches): a vertical error of `e` metres seen from `d` metres spans at most
//! `e * h / (2 d tan(fov_y / 2))` pixels on a viewport `h` pixels high, with `d` the distance
//! from the viewpoint to the nearest point of the tile's bounding box (conservative: no
//! point of the tile is nearer). Per-level errors are the manifest's `mask_errors_m`,
//! measured by the builder with the same triangulation the strips draw.

/// Pixels per metre of vertical error at `distance_m` for a viewport `height_px` high with a
/// vertical field of view `fov_y` (radians). Infinite at distance 0.
pub fn pixels_per_metre(distance_m: f64, fov_y: f64, height_px: f64) -> f64 {
    pixels_at_one_metre(fov_y, height_px) / distance_m.max(0.0)
}

/// Pixels a metre spans at a distance of one metre: [`pixels_per_metre`] is this over the
/// distance. Computed once per frame (it takes a tangent).
pub fn pixels_at_one_metre(fov_y: f64, height_px: f64) -> f64 {
    height_px / (2.0 * (fov_y / 2.0).tan())
}

/// The suffix minima of per-level errors: entry `l` is the least error of levels `l` and
/// coarser. Non-decreasing, so [`coarsest_level_within`] can search it by halves; computed
/// once per tile (the manifest's errors are not always monotone: a coarser mask can
/// happen to fit the surface better).
pub fn suffix_minima(mask_errors_m: &[f32]) -> Vec<f32> {
    let mut out = mask_errors_m.to_vec();
    for l in (0..out.len().saturating_sub(1)).rev() {
        out[l] = out[l].min(out[l + 1]);
    }
    out
}

/// The coarsest level whose error, at `pixels_per_metre`, is at most `threshold_px`, given
/// the tile's [`suffix_minima`]: the largest `l` with `minima[l] * k <= threshold` is the
/// largest level whose own error is within it. Level 0 (no error) always qualifies.
/// O(log levels).
pub fn coarsest_level_within(minima: &[f32], pixels_per_metre: f64, threshold_px: f64) -> u32 {
    // The largest error allowed, metres; far tiles (most of them) pass at the coarsest level.
    let limit = threshold_px / pixels_per_metre;
    match minima.last() {
        Some(&e) if f64::from(e) <= limit => minima.len() as u32 - 1,
        _ => (minima.partition_point(|&e| f64::from(e) <= limit)).saturating_sub(1) as u32,
    }
}

/// Distance from `eye` to the nearest point of the box from `min` to `max` (0 inside).
pub fn distance_to_box(eye: [f64; 3], min: [f64; 3], max: [f64; 3]) -> f64 {
    (0..3)
        .map(|i| {
            let d = (min[i] - eye[i]).max(eye[i] - max[i]).max(0.0);
            d * d
        })
        .sum::<f64>()
        .sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_flat_tile_needs_the_coarsest_mask_at_any_distance() {
        let flat = vec![0.0f32; 128];
        for distance in [0.5, 10.0, 1e4] {
            let k = pixels_per_metre(distance, 1.0, 1080.0);
            assert_eq!(coarsest_level_within(&flat, k, 1.0), 127);
        }
    }

    #[test]
    fn nearer_tiles_need_finer_masks_and_the_threshold_holds() {
        // Errors growing with the level, as on rough terrain.
        let errors: Vec<f32> = (0..128).map(|l| l as f32 * 0.5).collect();
        let mut previous = 0;
        for distance in [100.0, 1_000.0, 10_000.0, 100_000.0] {
            let k = pixels_per_metre(distance, 0.96, 540.0);
            let level = coarsest_level_within(&errors, k, 1.0);
            assert!(f64::from(errors[level as usize]) * k <= 1.0);
            if (level as usize) + 1 < errors.len() {
                assert!(
                    f64::from(errors[level as usize + 1]) * k > 1.0,
                    "the coarsest within"
                );
            }
            assert!(level >= previous, "farther never needs a finer mask");
            previous = level;
        }
        // Inside the box the distance is 0: only the exact level 0 qualifies.
        assert_eq!(
            coarsest_level_within(&errors, pixels_per_metre(0.0, 0.96, 540.0), 1.0),
            0
        );
    }

    #[test]
    fn the_search_over_suffix_minima_finds_what_a_scan_of_the_errors_finds() {
        // Errors that are not monotone: level 3 fits better than level 2.
        let errors = [0.0f32, 0.2, 0.9, 0.3, 1.5, 0.4, 2.0, 3.0];
        let minima = suffix_minima(&errors);
        assert_eq!(minima, vec![0.0, 0.2, 0.3, 0.3, 0.4, 0.4, 2.0, 3.0]);
        for k in [0.1, 0.5, 1.0, 2.0, 2.6, 3.0, 4.0, 1e3] {
            let scan = (0..errors.len())
                .rev()
                .find(|&l| f64::from(errors[l]) * k <= 1.0)
                .unwrap_or(0) as u32;
            assert_eq!(coarsest_level_within(&minima, k, 1.0), scan, "k = {k}");
        }
    }

    #[test]
    fn the_projection_matches_the_pinhole_model() {
        // 90 degrees over 1000 px: at 500 m, one metre spans one pixel.
        let k = pixels_per_metre(500.0, std::f64::consts::FRAC_PI_2, 1000.0);
        assert!((k - 1.0).abs() < 1e-12);
        assert_eq!(
            distance_to_box([0.0, 0.0, 0.0], [3.0, -1.0, 4.0], [5.0, 1.0, 6.0]),
            5.0
        );
        assert_eq!(
            distance_to_box([4.0, 0.0, 5.0], [3.0, -1.0, 4.0], [5.0, 1.0, 6.0]),
            0.0
        );
    }
}
