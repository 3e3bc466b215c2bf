//! Error metrics of a frame against the true surface and a reference frame.
//!
//! A frame is given per pixel as what it shows: the background (`None`) or the surface at a
//! world point (`Some([x, y, z])`, metres; x east, y south, z up), row-major from the top
//! left, as a position buffer read back from the renderer gives it.
//!
//! - **Screen-space geometric error** (as in Löffler et al.'s error-bounded projective grid,
//!   and the screen-space error of Yusov and Turlapov): at a pixel showing the surface at
//!   `(x, y, z)` where the true surface is at height `H(x, y)`, the distance in pixels
//!   between the projections of `(x, y, z)` and `(x, y, H)`: how far on screen the drawn
//!   surface is from the true one. Summarised as mean, max and the share of terrain pixels
//!   above a threshold (1 px by default).
//! - **Crack pixels**: pixels showing the background where the reference shows terrain.
//! - **PSNR** of the colours against the reference's, over RGB.

use crate::render::Camera;
use glam::DVec3;

/// What one pixel shows: `None` for the background, else the world point of the surface.
pub type Pixel = Option<[f64; 3]>;

/// Default threshold of [`ErrorStats::above_threshold`], pixels.
pub const DEFAULT_THRESHOLD_PX: f64 = 1.0;

/// Screen-space error over a frame's terrain pixels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ErrorStats {
    /// Pixels showing terrain whose true height is known.
    pub terrain_pixels: u64,
    pub mean_px: f64,
    /// 95th and 99th percentiles of the per-pixel error (nearest rank).
    pub p95_px: f64,
    pub p99_px: f64,
    pub max_px: f64,
    pub threshold_px: f64,
    /// Terrain pixels whose error exceeds `threshold_px`.
    pub above_threshold: u64,
    /// The [`LARGEST`] largest errors, largest first (0 past the terrain pixels).
    pub largest_px: [f64; LARGEST],
}

/// How many of the largest errors [`ErrorStats`] keeps.
pub const LARGEST: usize = 32;

impl ErrorStats {
    /// Share of terrain pixels above the threshold, in [0, 1] (0 without terrain pixels).
    pub fn share_above(&self) -> f64 {
        if self.terrain_pixels == 0 {
            0.0
        } else {
            self.above_threshold as f64 / self.terrain_pixels as f64
        }
    }

    /// The largest error once the `set_aside` largest are set aside (the maximum for 0).
    /// Past [`LARGEST`] it answers the smallest error kept, which is at least as large.
    pub fn max_after_px(&self, set_aside: u64) -> f64 {
        self.largest_px[(set_aside as usize).min(LARGEST - 1)]
    }
}

/// Where `world` lands on a `width` x `height` target seen by `camera`, in pixels from the
/// top left; `None` behind the camera.
pub fn project(camera: &Camera, width: u32, height: u32, world: [f64; 3]) -> Option<[f64; 2]> {
    let aspect = f64::from(width) / f64::from(height.max(1));
    let relative = Camera::to_render(DVec3::from(world) - DVec3::from(camera.position));
    let clip = camera.view_proj(aspect) * relative.extend(1.0);
    if clip.w <= 0.0 {
        return None;
    }
    Some([
        (clip.x / clip.w + 1.0) * 0.5 * f64::from(width),
        (1.0 - clip.y / clip.w) * 0.5 * f64::from(height),
    ])
}

/// The screen-space geometric error of `frame` (see the module docs), given the true
/// surface's height at any point (`None` where it is unknown: off the terrain).
pub fn screen_space_error(
    frame: &[Pixel],
    width: u32,
    height: u32,
    camera: &Camera,
    true_height: impl Fn(f64, f64) -> Option<f64>,
    threshold_px: f64,
) -> ErrorStats {
    assert_eq!(
        frame.len(),
        (width * height) as usize,
        "one entry per pixel"
    );
    let mut stats = ErrorStats {
        terrain_pixels: 0,
        mean_px: 0.0,
        p95_px: 0.0,
        p99_px: 0.0,
        max_px: 0.0,
        threshold_px,
        above_threshold: 0,
        largest_px: [0.0; LARGEST],
    };
    let mut sum = 0.0;
    let mut errors = Vec::new();
    for point in frame.iter().flatten() {
        let Some(h) = true_height(point[0], point[1]) else {
            continue;
        };
        let (Some(drawn), Some(truth)) = (
            project(camera, width, height, *point),
            project(camera, width, height, [point[0], point[1], h]),
        ) else {
            continue;
        };
        let error = (drawn[0] - truth[0]).hypot(drawn[1] - truth[1]);
        stats.terrain_pixels += 1;
        sum += error;
        errors.push(error);
        stats.max_px = stats.max_px.max(error);
        if error > threshold_px {
            stats.above_threshold += 1;
        }
    }
    if stats.terrain_pixels > 0 {
        stats.mean_px = sum / stats.terrain_pixels as f64;
    }
    // The largest few, without sorting them all: partition them to the front, then sort
    // those (the percentiles below reorder `errors` anyway).
    let kept = LARGEST.min(errors.len());
    if kept > 0 {
        errors.select_nth_unstable_by(kept - 1, |a, b| b.total_cmp(a));
        errors[..kept].sort_unstable_by(|a, b| b.total_cmp(a));
        stats.largest_px[..kept].copy_from_slice(&errors[..kept]);
    }
    stats.p95_px = percentile(&mut errors, 95.0);
    stats.p99_px = percentile(&mut errors, 99.0);
    stats
}

/// The `p`-th percentile of `values` by nearest rank (the smallest value at or above `p`% of
/// them); 0 when empty. Reorders `values`.
pub fn percentile(values: &mut [f64], p: f64) -> f64 {
    if values.is_empty() {
        return 0.0;
    }
    let rank = ((p / 100.0 * values.len() as f64).ceil() as usize).clamp(1, values.len());
    *values.select_nth_unstable_by(rank - 1, f64::total_cmp).1
}

/// Pixels where `frame` shows the background and `reference` shows terrain.
pub fn crack_pixels(frame: &[Pixel], reference: &[Pixel]) -> u64 {
    assert_eq!(frame.len(), reference.len(), "frames of the same size");
    frame
        .iter()
        .zip(reference)
        .filter(|(f, r)| f.is_none() && r.is_some())
        .count() as u64
}

/// Pixels where `frame` shows the background, `reference` shows terrain, and `frame` shows
/// terrain both above and below in the same column (`width` pixels a row): holes in the
/// surface, the cracks proper. A background pixel where only a silhouette moved (a coarser
/// mesh lower against the sky) has no terrain above it and is not counted.
pub fn enclosed_holes(frame: &[Pixel], reference: &[Pixel], width: u32) -> u64 {
    assert_eq!(frame.len(), reference.len(), "frames of the same size");
    let width = width as usize;
    let height = frame.len() / width.max(1);
    let mut count = 0;
    for x in 0..width {
        let column = |y: usize| y * width + x;
        let Some(top) = (0..height).find(|&y| frame[column(y)].is_some()) else {
            continue;
        };
        let bottom = (0..height)
            .rev()
            .find(|&y| frame[column(y)].is_some())
            .unwrap_or(top);
        count += (top..bottom)
            .filter(|&y| frame[column(y)].is_none() && reference[column(y)].is_some())
            .count() as u64;
    }
    count
}

/// Peak signal-to-noise ratio of `frame`'s colours against `reference`'s, RGB, in dB;
/// infinite for identical images.
pub fn psnr(frame: &image::RgbaImage, reference: &image::RgbaImage) -> f64 {
    assert_eq!(
        frame.dimensions(),
        reference.dimensions(),
        "images of the same size"
    );
    let (mut sum, mut n) = (0.0f64, 0u64);
    for (a, b) in frame.pixels().zip(reference.pixels()) {
        for c in 0..3 {
            let d = f64::from(a.0[c]) - f64::from(b.0[c]);
            sum += d * d;
            n += 1;
        }
    }
    let mse = sum / n.max(1) as f64;
    if mse == 0.0 {
        f64::INFINITY
    } else {
        10.0 * (255.0f64 * 255.0 / mse).log10()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const W: u32 = 64;
    const H: u32 = 48;

    /// A camera 100 m above flat ground at height 0, looking east and down.
    fn camera() -> Camera {
        Camera::new([0.0, 0.0, 100.0], 0.0, -0.4)
    }

    /// A frame whose pixels all show points of flat ground at height `z` in front of the
    /// camera (a third of them background), as a position buffer would hold them.
    fn flat_frame(z: f64) -> Vec<Pixel> {
        (0..W * H)
            .map(|i| {
                let (x, y) = (f64::from(i % W), f64::from(i / W));
                (i % 3 != 0).then_some([50.0 + 10.0 * y, (x - 32.0) * 5.0, z])
            })
            .collect()
    }

    #[test]
    fn a_frame_on_the_true_surface_has_no_error_and_no_crack() {
        let camera = camera();
        let frame = flat_frame(0.0);
        let stats = screen_space_error(&frame, W, H, &camera, |_, _| Some(0.0), 1.0);
        assert!(stats.terrain_pixels > (W * H / 3) as u64, "{stats:?}");
        assert_eq!(stats.max_px, 0.0);
        assert_eq!(stats.above_threshold, 0);
        assert_eq!(crack_pixels(&frame, &frame), 0);
        let image = image::RgbaImage::from_pixel(W, H, image::Rgba([10, 200, 30, 255]));
        assert!(psnr(&image, &image).is_infinite());
    }

    #[test]
    fn percentiles_are_nearest_ranks() {
        let mut values: Vec<f64> = (1..=200).rev().map(f64::from).collect();
        assert_eq!(percentile(&mut values, 95.0), 190.0);
        assert_eq!(percentile(&mut values, 99.0), 198.0);
        assert_eq!(percentile(&mut values, 100.0), 200.0);
        // Nine and a half of ten values: the rank rounds up.
        let mut ten: Vec<f64> = (1..=10).map(f64::from).collect();
        assert_eq!(percentile(&mut ten, 95.0), 10.0);
        assert_eq!(percentile(&mut [7.0], 99.0), 7.0);
        assert_eq!(percentile(&mut [], 99.0), 0.0);
        // One pixel in a hundred far off moves the maximum, not the 99th percentile.
        let camera = Camera::new([0.0, 0.0, 0.0], 0.0, 0.0);
        let mut frame = vec![None; (W * H) as usize];
        for (i, p) in frame.iter_mut().take(100).enumerate() {
            *p = Some([500.0, 0.0, if i == 0 { 30.0 } else { 0.0 }]);
        }
        let stats = screen_space_error(&frame, W, H, &camera, |_, _| Some(0.0), 1.0);
        assert_eq!((stats.p95_px, stats.p99_px), (0.0, 0.0));
        assert!(stats.max_px > 1.0);
        // The one outlier set aside, the largest error left is 0.
        assert_eq!(stats.max_after_px(0), stats.max_px);
        assert_eq!(stats.max_after_px(1), 0.0);
    }

    #[test]
    fn the_largest_errors_are_kept_largest_first() {
        let camera = Camera::new([0.0, 0.0, 0.0], 0.0, 0.0);
        // Pixel i at 500 m east, i metres off: errors grow with i.
        let frame: Vec<Pixel> = (0..(W * H))
            .map(|i| (i < 100).then(|| [500.0, 0.0, f64::from(i)]))
            .collect();
        let stats = screen_space_error(&frame, W, H, &camera, |_, _| Some(0.0), 1.0);
        let each = |m: f64| m * (f64::from(H) / 2.0) / (500.0 * (camera.fov_y / 2.0).tan());
        for k in 0..LARGEST as u64 {
            let expected = each(99.0 - k as f64);
            assert!((stats.max_after_px(k) - expected).abs() < 1e-9, "{k}");
        }
        // Past what is kept: the smallest kept, at least as large as the true answer.
        assert_eq!(stats.max_after_px(1000), stats.largest_px[LARGEST - 1]);
    }

    #[test]
    fn a_known_vertical_offset_gives_the_pinhole_pixel_error() {
        // Looking level at a point 500 m east: a vertical error of e metres spans
        // e * (H / 2) / (500 tan(fov / 2)) pixels.
        let camera = Camera::new([0.0, 0.0, 0.0], 0.0, 0.0);
        let offset = 3.0;
        let mut frame = vec![None; (W * H) as usize];
        frame[0] = Some([500.0, 0.0, offset]);
        let stats = screen_space_error(&frame, W, H, &camera, |_, _| Some(0.0), 1.0);
        let expected = offset * (f64::from(H) / 2.0) / (500.0 * (camera.fov_y / 2.0).tan());
        assert_eq!(stats.terrain_pixels, 1);
        assert!(
            (stats.max_px - expected).abs() < 1e-9,
            "{} vs {expected}",
            stats.max_px
        );
        assert_eq!(stats.above_threshold, u64::from(expected > 1.0));
        // The same offset twice as far spans half as many pixels.
        frame[0] = Some([1000.0, 0.0, offset]);
        let far = screen_space_error(&frame, W, H, &camera, |_, _| Some(0.0), 1.0);
        assert!((far.max_px - expected / 2.0).abs() < 1e-9);
    }

    #[test]
    fn a_hole_of_known_size_is_counted() {
        let reference: Vec<Pixel> = vec![Some([0.0, 0.0, 0.0]); (W * H) as usize];
        let mut frame = reference.clone();
        for y in 10..17 {
            for x in 20..31 {
                frame[(y * W + x) as usize] = None;
            }
        }
        assert_eq!(crack_pixels(&frame, &reference), 7 * 11);
        // Enclosed by terrain above and below: all of it is a crack.
        assert_eq!(enclosed_holes(&frame, &reference, W), 7 * 11);
        // The top rows lost against the sky (a lower silhouette) are not cracks.
        let mut lowered = reference.clone();
        for p in lowered.iter_mut().take((3 * W) as usize) {
            *p = None;
        }
        assert_eq!(crack_pixels(&lowered, &reference), u64::from(3 * W));
        assert_eq!(enclosed_holes(&lowered, &reference, W), 0);
        // Background in both is not a crack.
        assert_eq!(crack_pixels(&[None; 4], &[None; 4]), 0);
    }

    #[test]
    fn psnr_falls_as_colours_differ() {
        let a = image::RgbaImage::from_pixel(8, 8, image::Rgba([100, 100, 100, 255]));
        let b = image::RgbaImage::from_pixel(8, 8, image::Rgba([110, 100, 100, 255]));
        let c = image::RgbaImage::from_pixel(8, 8, image::Rgba([140, 100, 100, 255]));
        // One channel off by 10: MSE 100 / 3.
        let expected = 10.0 * (255.0f64 * 255.0 / (100.0 / 3.0)).log10();
        assert!((psnr(&b, &a) - expected).abs() < 1e-9);
        assert!(psnr(&c, &a) < psnr(&b, &a));
    }
}
