//! A rendered frame as the metrics see it, and its measures against a reference.
//!
//! The renderer keeps the frame's depth buffer (reversed depth, 0 for the background); each
//! pixel's depth, through the inverse of the camera's projection, gives the world point it
//! shows ([`positions_from_depth`]). A frame drawn with a crack filler is compared with
//! the same frame drawn without one: the pixels whose depth differs show the filler.

use super::metrics::{self, ErrorStats, Pixel};
use crate::render::Camera;
use glam::{DVec3, DVec4};

/// The world points of a `width` x `height` frame seen by `camera`, from its depth buffer
/// (row-major from the top left, reversed depth, 0 where nothing was drawn), sampled at
/// pixel centres.
pub fn positions_from_depth(depth: &[f32], width: u32, height: u32, camera: &Camera) -> Vec<Pixel> {
    let aspect = f64::from(width) / f64::from(height.max(1));
    let inverse = camera.view_proj(aspect).inverse();
    let eye = DVec3::from(camera.position);
    depth
        .iter()
        .enumerate()
        .map(|(i, &d)| {
            if d <= 0.0 {
                return None;
            }
            let (x, y) = ((i as u32 % width) as f64, (i as u32 / width) as f64);
            let ndc = DVec4::new(
                (x + 0.5) / f64::from(width) * 2.0 - 1.0,
                1.0 - (y + 0.5) / f64::from(height) * 2.0,
                f64::from(d),
                1.0,
            );
            let p = inverse * ndc;
            let relative = p.truncate() / p.w;
            // Render space (east, up, south) back to world (east, south, up).
            Some((eye + Camera::to_render(relative)).to_array())
        })
        .collect()
}

/// One frame's pixels as measured: colour, depth and the world points.
#[derive(Debug, Clone)]
pub struct Capture {
    pub color: image::RgbaImage,
    pub depth: Vec<f32>,
    pub points: Vec<Pixel>,
}

impl Capture {
    /// A capture of `color` and `depth` seen by `camera`.
    pub fn new(color: image::RgbaImage, depth: Vec<f32>, camera: &Camera) -> Capture {
        let points = positions_from_depth(&depth, color.width(), color.height(), camera);
        Capture {
            color,
            depth,
            points,
        }
    }

    /// Pixels showing terrain (anything but the background).
    pub fn terrain_pixels(&self) -> u64 {
        self.points.iter().filter(|p| p.is_some()).count() as u64
    }
}

/// A frame's measures against its reference.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameMeasures {
    /// Screen-space geometric error of every pixel showing the surface or a filler.
    pub error: ErrorStats,
    /// The same of the frame drawn without its filler (same masks), when it has one: what
    /// the filler's pixels add to it is the difference.
    pub unfilled_error: Option<ErrorStats>,
    /// Pixels where the reference shows terrain and the frame a filler filling a crack, or
    /// the background with terrain above and below it ([`metrics::enclosed_holes`]): the
    /// cracks of the frame's mesh, filled or not.
    pub crack_pixels: u64,
    /// Of those, the pixels left showing the background.
    pub hole_pixels: u64,
    /// Pixels where the reference shows terrain and the frame the sky above its own
    /// silhouette: a coarser surface lower against the sky, not a crack.
    pub silhouette_pixels: u64,
    /// Pixels showing a crack filler.
    pub filler_pixels: u64,
    /// Of those, the pixels showing it where the mesh has no crack ([`Unfilled::probe`]):
    /// past a skyline, past the terrain's border, in front of a lower surface.
    pub leak_pixels: u64,
    /// Pixels where the reference shows terrain.
    pub reference_terrain_pixels: u64,
    /// Of those, the pixels where the frame shows terrain or a filler too.
    pub covered_pixels: u64,
    /// Colour PSNR against the reference, dB (infinite when identical).
    pub psnr_db: f64,
}

/// The same frame as a filled one, drawn without its filler and with the crack probe.
#[derive(Debug, Clone, PartialEq)]
pub struct Unfilled {
    /// Depth of the frame drawn without a filler: where the filled frame's differs, the
    /// filler shows.
    pub depth: Vec<f32>,
    /// Depth of the frame drawn with the crack probe: where it differs from `depth`, the
    /// mesh has a crack.
    pub probe: Vec<f32>,
}

/// Measures `frame` against `reference` (same camera and size). `unfilled` is the same frame
/// drawn without its crack filler and with the crack probe (`None` when it has no filler).
/// `true_height` gives the true surface's height.
pub fn measure(
    frame: &Capture,
    unfilled: Option<&Unfilled>,
    reference: &Capture,
    camera: &Camera,
    true_height: impl Fn(f64, f64) -> Option<f64>,
    threshold_px: f64,
) -> FrameMeasures {
    let (width, height) = frame.color.dimensions();
    let error = metrics::screen_space_error(
        &frame.points,
        width,
        height,
        camera,
        &true_height,
        threshold_px,
    );
    let unfilled_error = unfilled.map(|u| {
        metrics::screen_space_error(
            &positions_from_depth(&u.depth, width, height, camera),
            width,
            height,
            camera,
            &true_height,
            threshold_px,
        )
    });
    // Per pixel: whether the filler shows, and whether the mesh has a crack there.
    let (filler, crack): (Vec<bool>, Vec<bool>) = match unfilled {
        Some(unfilled) => frame
            .depth
            .iter()
            .zip(&unfilled.depth)
            .zip(&unfilled.probe)
            .map(|((filled, bare), probe)| (filled != bare, probe != bare))
            .unzip(),
        None => (
            vec![false; frame.depth.len()],
            vec![false; frame.depth.len()],
        ),
    };
    let background = metrics::crack_pixels(&frame.points, &reference.points);
    let hole_pixels = metrics::enclosed_holes(&frame.points, &reference.points, width);
    let filled = frame
        .points
        .iter()
        .zip(&reference.points)
        .zip(filler.iter().zip(&crack))
        .filter(|((f, r), (filler, crack))| **filler && **crack && f.is_some() && r.is_some())
        .count() as u64;
    FrameMeasures {
        error,
        unfilled_error,
        crack_pixels: hole_pixels + filled,
        hole_pixels,
        silhouette_pixels: background - hole_pixels,
        filler_pixels: filler.iter().filter(|&&f| f).count() as u64,
        leak_pixels: filler
            .iter()
            .zip(&crack)
            .filter(|&(&f, &c)| f && !c)
            .count() as u64,
        reference_terrain_pixels: reference.terrain_pixels(),
        covered_pixels: frame
            .points
            .iter()
            .zip(&reference.points)
            .filter(|(f, r)| f.is_some() && r.is_some())
            .count() as u64,
        psnr_db: metrics::psnr(&frame.color, &reference.color),
    }
}

/// `frame` with its filler's pixels marked against `unfilled` and `reference`: green where
/// the filler fills a crack, red where it leaks (shows where the mesh has no crack), blue
/// where a crack is left showing the background (a hole; magenta where the crack probe saw
/// no crack there); the rest dimmed.
pub fn filler_picture(
    frame: &Capture,
    unfilled: &Unfilled,
    reference: &Capture,
) -> image::RgbaImage {
    let width = frame.color.width() as usize;
    let mut picture = frame.color.clone();
    let holes: Vec<bool> = {
        let mut holes = vec![false; frame.points.len()];
        let height = frame.points.len() / width.max(1);
        for x in 0..width {
            let column: Vec<usize> = (0..height).map(|y| y * width + x).collect();
            let drawn: Vec<usize> = column
                .iter()
                .copied()
                .filter(|&i| frame.points[i].is_some())
                .collect();
            if let (Some(&top), Some(&bottom)) = (drawn.first(), drawn.last()) {
                for i in (top..bottom).step_by(width) {
                    holes[i] = frame.points[i].is_none() && reference.points[i].is_some();
                }
            }
        }
        holes
    };
    for (i, pixel) in picture.pixels_mut().enumerate() {
        let filler = frame.depth[i] != unfilled.depth[i];
        let crack = unfilled.probe[i] != unfilled.depth[i];
        pixel.0 = match (filler, crack, holes[i]) {
            (true, true, _) => [0, 220, 0, 255],
            (true, false, _) => [255, 0, 0, 255],
            (_, true, true) => [0, 80, 255, 255],
            (_, false, true) => [255, 0, 255, 255],
            _ => {
                let [r, g, b, a] = pixel.0;
                [r / 3, g / 3, b / 3, a]
            }
        };
    }
    picture
}

impl FrameMeasures {
    /// Share of the reference's terrain pixels the frame draws, in [0, 1] (1 when the
    /// reference shows no terrain).
    pub fn coverage(&self) -> f64 {
        if self.reference_terrain_pixels == 0 {
            1.0
        } else {
            self.covered_pixels as f64 / self.reference_terrain_pixels as f64
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn depth_is_turned_back_into_the_point_it_came_from() {
        let camera = Camera::new([100.0, 200.0, 50.0], 0.7, -0.3);
        let (w, h) = (40u32, 30u32);
        let aspect = f64::from(w) / f64::from(h);
        let m = camera.view_proj(aspect);
        // Project known points, write their depth at their pixel, read them back.
        let mut depth = vec![0.0f32; (w * h) as usize];
        let mut expected = Vec::new();
        for k in 0..20 {
            let world = DVec3::new(
                300.0 + 13.0 * f64::from(k),
                400.0 + 7.0 * f64::from(k),
                f64::from(k),
            );
            let clip = m * Camera::to_render(world - DVec3::from(camera.position)).extend(1.0);
            let ndc = clip.truncate() / clip.w;
            let px = ((ndc.x + 1.0) * 0.5 * f64::from(w)).floor();
            let py = ((1.0 - ndc.y) * 0.5 * f64::from(h)).floor();
            if !(0.0..f64::from(w)).contains(&px) || !(0.0..f64::from(h)).contains(&py) {
                continue;
            }
            let i = (py as u32 * w + px as u32) as usize;
            if depth[i] != 0.0 {
                continue; // one point a pixel
            }
            depth[i] = ndc.z as f32;
            expected.push((i, world, ndc.z));
        }
        assert!(expected.len() > 5);
        let points = positions_from_depth(&depth, w, h, &camera);
        for (i, world, _) in &expected {
            let p = DVec3::from(points[*i].expect("drawn"));
            // Same depth, pixel centre instead of the exact point: on the same view ray
            // within half a pixel, at the same distance along the view axis.
            let along = |q: DVec3| (q - DVec3::from(camera.position)).dot(camera.direction());
            assert!(
                (along(p) - along(*world)).abs() < 1e-3 * along(*world),
                "{p} vs {world}"
            );
        }
        assert_eq!(
            points.iter().filter(|p| p.is_some()).count(),
            expected.len()
        );
    }

    fn capture(points: Vec<Pixel>, depth: Vec<f32>, grey: u8) -> Capture {
        Capture {
            color: image::RgbaImage::from_pixel(1, 4, image::Rgba([grey, grey, grey, 255])),
            depth,
            points,
        }
    }

    #[test]
    fn holes_and_filled_cracks_are_told_apart() {
        let camera = Camera::new([0.0, 0.0, 100.0], 0.0, -0.4);
        let ground = Some([300.0, 0.0, 0.0]);
        let reference = capture(vec![ground; 4], vec![0.5; 4], 100);
        // Pixel 1 is a hole; pixels 0 and 2 show the filler (their depth differs from the
        // unfilled frame's) where the probe finds a crack (its depth differs too); pixel 3
        // shows the filler in front of the surface, where the probe shows the surface too:
        // a leak.
        let frame = capture(
            vec![
                Some([300.0, 0.0, -20.0]),
                None,
                Some([300.0, 0.0, -40.0]),
                Some([300.0, 0.0, -30.0]),
            ],
            vec![0.45, 0.0, 0.4, 0.6],
            100,
        );
        let unfilled = Unfilled {
            depth: vec![0.5, 0.0, 0.0, 0.5],
            probe: vec![0.45, 0.3, 0.3, 0.5],
        };
        // A 1 x 4 frame (one column) spans few pixels: a threshold of a twentieth of one.
        let m = measure(
            &frame,
            Some(&unfilled),
            &reference,
            &camera,
            |_, _| Some(0.0),
            0.05,
        );
        assert_eq!(
            (
                m.crack_pixels,
                m.hole_pixels,
                m.filler_pixels,
                m.leak_pixels
            ),
            (3, 1, 3, 1)
        );
        assert_eq!(m.reference_terrain_pixels, 4);
        // Pixel 1 shows the background: three of the reference's four terrain pixels drawn.
        assert_eq!(m.covered_pixels, 3);
        assert!((m.coverage() - 0.75).abs() < 1e-12);
        // The filler pixels lie 20 to 40 m under the surface: the three with an error.
        assert_eq!(m.error.terrain_pixels, 3);
        assert_eq!(m.error.above_threshold, 3);
        // The unfilled frame is measured too: its two surface pixels.
        assert_eq!(m.unfilled_error.map(|e| e.terrain_pixels), Some(2));
        // Against itself: nothing.
        let same = measure(&reference, None, &reference, &camera, |_, _| Some(0.0), 1.0);
        assert_eq!(
            (same.crack_pixels, same.filler_pixels, same.leak_pixels),
            (0, 0, 0)
        );
        assert_eq!(same.error.max_px, 0.0);
        assert!(same.psnr_db.is_infinite());
        assert!(same.unfilled_error.is_none());
    }
}
