//! The fewest triangles a frame needs: per tile, the coarsest level (strip mask or GeoMipMap)
//! whose vertical error, projected to the screen, stays within a threshold in pixels. What a
//! frame draws, set against this, says whether it models more than the scene needs (a flat
//! tile needs two triangles whatever the budget).
//!
//! **The bound** ([`ErrorProjection`]). The accuracy measures ([`crate::eval`]) take, for
//! every pixel, the point `P` drawn there and the true surface's point `Q` straight above or
//! below it, `e` metres away, and count the pixels between their projections. With `P` at
//! view depth `z` and `t` the tangent of its angle off the view axis, that distance is
//! exactly `f * e * |u_xy - t u_z| / (z + e u_z)` for the unit vertical `u` in view space
//! (`f` the focal length in pixels), hence at most `f * e * sqrt(1 + t^2) / (z - e)`. Over a
//! tile, `z` is at least the view depth of its bounding box's nearest corner (and at least
//! the near plane: nothing nearer is drawn), and `t` at most what the box's circumscribed
//! sphere allows (the centre's distance from the axis plus the radius, over the centre's
//! depth less the radius), and at most the viewport corner's. So a level whose error `e` satisfies `e <= tau * z / (f sec + tau)`
//! keeps every pixel of the tile within `tau` pixels: [`ErrorProjection::pixels_per_metre`]
//! is the `(f sec + tau) / z` that [`coarsest_level_within`] compares with. (Dividing by the
//! Euclidean distance to the box instead, the textbook bound, is not one: off the view axis
//! the depth is smaller than the distance, and at a 16:9 viewport's corner that
//! underestimates the error by a factor of up to 2.4.) Per-level errors are the manifest's
//! `mask_errors_m` for strip masks, measured by the builder with the triangulation the strips
//! draw, and [`crate::method::geomipmap::stitching::level_errors`] for GeoMipMaps.

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
    coarsest_level_within_raised(minima, 0.0, pixels_per_metre, threshold_px)
}

/// [`coarsest_level_within`] with every error raised by `raise_m` metres (a coarser level
/// of the pyramid is that far from full resolution already), without a raised copy.
pub fn coarsest_level_within_raised(
    minima: &[f32],
    raise_m: f32,
    pixels_per_metre: f64,
    threshold_px: f64,
) -> u32 {
    // The largest error allowed, metres; far tiles (most of them) pass at the coarsest level.
    let limit = threshold_px / pixels_per_metre;
    let within = |&e: &f32| f64::from(e + raise_m) <= limit;
    match minima.last() {
        Some(e) if within(e) => minima.len() as u32 - 1,
        _ => (minima.partition_point(within)).saturating_sub(1) as u32,
    }
}

/// Per-frame constants of the screen-space error bound (see the module documentation).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ErrorProjection {
    eye: [f64; 3],
    /// Unit view direction, in the same (world) frame as `eye`.
    forward: [f64; 3],
    /// Focal length, pixels: [`pixels_at_one_metre`].
    focal_px: f64,
    /// Squared tangent of the angle between the view axis and the viewport's corner.
    tan2_corner: f64,
    near: f64,
}

impl ErrorProjection {
    /// The bound for a camera at `eye` looking along `forward` with a vertical field of view
    /// `fov_y` (radians) onto a viewport of `viewport` pixels, near plane at `near` metres.
    pub fn new(
        eye: [f64; 3],
        forward: [f64; 3],
        fov_y: f64,
        viewport: [u32; 2],
        near: f64,
    ) -> ErrorProjection {
        let length = forward
            .iter()
            .map(|c| c * c)
            .sum::<f64>()
            .sqrt()
            .max(1e-300);
        let aspect = f64::from(viewport[0]) / f64::from(viewport[1].max(1));
        let tan_y = (fov_y / 2.0).tan();
        ErrorProjection {
            eye,
            forward: forward.map(|c| c / length),
            focal_px: pixels_at_one_metre(fov_y, f64::from(viewport[1])),
            tan2_corner: tan_y * tan_y * (1.0 + aspect * aspect),
            near: near.max(1e-6),
        }
    }

    /// For a tile whose bounding box runs from `min` to `max`: the `k` such that an error of
    /// `e` metres with `e * k <= threshold_px` keeps every pixel the tile draws within
    /// `threshold_px` of the true surface, by the bound of the module documentation.
    pub fn pixels_per_metre(&self, min: [f64; 3], max: [f64; 3], threshold_px: f64) -> f64 {
        // The nearest view depth of the box, exactly: per axis the end the view looks from.
        let (mut depth, mut centre_z, mut centre2, mut radius2) = (0.0, 0.0, 0.0, 0.0);
        for i in 0..3 {
            let (lo, hi, f) = (min[i] - self.eye[i], max[i] - self.eye[i], self.forward[i]);
            depth += if f >= 0.0 { lo * f } else { hi * f };
            let (c, h) = ((lo + hi) * 0.5, (hi - lo) * 0.5);
            centre_z += c * f;
            centre2 += c * c;
            radius2 += h * h;
        }
        // The angle off the axis, bounded over the box's circumscribed sphere: no point of it
        // is farther from the axis than the centre plus the radius, nor nearer the eye's
        // plane than the centre minus the radius. One square root a tile.
        let radius = radius2.sqrt();
        let near_z = centre_z - radius;
        let tan2 = if near_z <= self.near {
            self.tan2_corner
        } else {
            let off_axis = (centre2 - centre_z * centre_z).max(0.0).sqrt() + radius;
            ((off_axis * off_axis) / (near_z * near_z)).min(self.tan2_corner)
        };
        let sec = (1.0 + tan2).sqrt();
        (self.focal_px * sec + threshold_px) / depth.max(self.near)
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

    /// Any point of a box drawn on a pinhole camera's viewport, raised or lowered by the
    /// largest error the bound allows, moves at most the threshold on the screen; and the
    /// bound is not loose on the view axis.
    #[test]
    fn the_bound_holds_for_every_drawn_point_of_the_box() {
        use glam::DVec3;
        let mut state = 0x9E37_79B9_7F4A_7C15u64;
        let mut random = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let (width, height, fov_y, near) = (640u32, 360u32, 55f64.to_radians(), 1.0);
        let focal = pixels_at_one_metre(fov_y, f64::from(height));
        let mut checked = 0;
        for _ in 0..400 {
            let eye = DVec3::new(random() * 2000.0, random() * 2000.0, random() * 800.0);
            let (yaw, pitch) = (random() * 6.3, (random() - 0.7) * 1.5);
            let forward = DVec3::new(
                yaw.cos() * pitch.cos(),
                yaw.sin() * pitch.cos(),
                pitch.sin(),
            );
            let right = forward.cross(DVec3::Z).normalize();
            let up = right.cross(forward);
            let min = DVec3::new(random() * 2000.0, random() * 2000.0, random() * 300.0);
            let max = min + DVec3::new(100.0, 100.0, random() * 200.0);
            let projection = ErrorProjection::new(
                eye.to_array(),
                forward.to_array(),
                fov_y,
                [width, height],
                near,
            );
            let threshold = 1.0;
            let e =
                threshold / projection.pixels_per_metre(min.to_array(), max.to_array(), threshold);
            let screen = |p: DVec3| {
                let d = p - eye;
                let z = d.dot(forward);
                (z > 0.0).then(|| [focal * d.dot(right) / z, focal * d.dot(up) / z])
            };
            let on_viewport = |s: [f64; 2]| {
                s[0].abs() <= f64::from(width) / 2.0 && s[1].abs() <= f64::from(height) / 2.0
            };
            for _ in 0..200 {
                let p = min + (max - min) * DVec3::new(random(), random(), random());
                let Some(drawn) = screen(p).filter(|&s| on_viewport(s)) else {
                    continue;
                };
                if (p - eye).dot(forward) < near {
                    continue;
                }
                for sign in [-1.0, 1.0] {
                    let Some(truth) = screen(p + DVec3::Z * (sign * e)) else {
                        panic!("the truth behind the camera: e = {e} is not within the bound");
                    };
                    let moved = (drawn[0] - truth[0]).hypot(drawn[1] - truth[1]);
                    assert!(
                        moved <= threshold * (1.0 + 1e-9),
                        "{moved} px > {threshold}"
                    );
                }
                checked += 1;
            }
        }
        assert!(checked > 10_000, "only {checked} points drawn");
        // On the axis, far away, the bound is the pinhole's: tight within the secant.
        let far = ErrorProjection::new([0.0; 3], [1.0, 0.0, 0.0], fov_y, [width, height], near);
        let k = far.pixels_per_metre([10_000.0, -1.0, -1.0], [10_002.0, 1.0, 1.0], 1.0);
        assert!((k / (focal / 10_000.0) - 1.0).abs() < 0.01, "{k}");
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
