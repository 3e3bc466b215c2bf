//! Popping: how much a method's frame jumps from the one before while the camera moves a
//! little, beyond what the reference's own frames change between the same cameras.
//!
//! A level of detail that switches a tile from one mask to another makes the surface jump
//! between two frames; a camera moving a few metres a frame changes the reference only a
//! little. So per pixel, the change of the method's frame between two consecutive cameras
//! has the reference's change at that pixel taken off, and what is left is measured:
//!
//! - **colour**: the mean over red, green and blue of `|(b - a) - (rb - ra)|` (0 to 255),
//!   with `a`, `b` the method's frames and `ra`, `rb` the reference's, over every pixel;
//! - **depth**: `|(db - da) - (drb - dra)|` with `d` the distance from the camera to the
//!   surface a pixel shows, in percent of the reference's distance at the second frame,
//!   over pixels showing terrain in all four frames.
//!
//! A method that draws what the reference draws, or keeps its level of detail while the
//! camera moves, differs from the reference's change only by its own error's drift; a
//! still camera gives zero. Mean and 99th percentile over the pixels of every pair of
//! frames. Pure: captures in, numbers out.

use super::frame::Capture;
use super::metrics::percentile;

/// Per-pixel changes gathered over a run of frames (see the module docs).
#[derive(Debug, Clone, Default)]
pub struct Changes {
    colour: Vec<f64>,
    depth_pct: Vec<f64>,
    /// Per pair of frames, its mean colour change.
    steps: Vec<f64>,
    /// Per pair of frames, its mean depth change (percent).
    depth_steps: Vec<f64>,
}

/// One frame: a method's capture and the reference's, from the camera at `eye`.
#[derive(Debug, Clone, Copy)]
pub struct Pair<'a> {
    pub method: &'a Capture,
    pub reference: &'a Capture,
    pub eye: [f64; 3],
}

impl Changes {
    /// Adds the changes from frame `a` to frame `b`.
    pub fn add(&mut self, a: Pair<'_>, b: Pair<'_>) {
        let before = self.colour.len();
        let pixels = a
            .method
            .color
            .pixels()
            .zip(b.method.color.pixels())
            .zip(a.reference.color.pixels().zip(b.reference.color.pixels()));
        for ((ma, mb), (ra, rb)) in pixels {
            let sum: f64 = (0..3)
                .map(|k| {
                    let method = f64::from(mb[k]) - f64::from(ma[k]);
                    let reference = f64::from(rb[k]) - f64::from(ra[k]);
                    (method - reference).abs()
                })
                .sum();
            self.colour.push(sum / 3.0);
        }
        let step = &self.colour[before..];
        if !step.is_empty() {
            self.steps
                .push(step.iter().sum::<f64>() / step.len() as f64);
        }
        let distance = |p: &[f64; 3], eye: [f64; 3]| {
            ((p[0] - eye[0]).powi(2) + (p[1] - eye[1]).powi(2) + (p[2] - eye[2]).powi(2)).sqrt()
        };
        let depth_before = self.depth_pct.len();
        let points = a
            .method
            .points
            .iter()
            .zip(&b.method.points)
            .zip(a.reference.points.iter().zip(&b.reference.points));
        for ((ma, mb), (ra, rb)) in points {
            if let (Some(ma), Some(mb), Some(ra), Some(rb)) = (ma, mb, ra, rb) {
                let method = distance(mb, b.eye) - distance(ma, a.eye);
                let reference = distance(rb, b.eye) - distance(ra, a.eye);
                let scale = distance(rb, b.eye);
                if scale > 0.0 {
                    self.depth_pct
                        .push(100.0 * (method - reference).abs() / scale);
                }
            }
        }
        let step = &self.depth_pct[depth_before..];
        self.depth_steps
            .push(step.iter().sum::<f64>() / step.len().max(1) as f64);
    }

    /// Mean and 99th percentile of the colour and depth changes gathered.
    pub fn summary(&self) -> Popping {
        let mean = |v: &[f64]| {
            if v.is_empty() {
                0.0
            } else {
                v.iter().sum::<f64>() / v.len() as f64
            }
        };
        Popping {
            colour_mean: mean(&self.colour),
            colour_p99: percentile(&mut self.colour.clone(), 99.0),
            depth_mean_pct: mean(&self.depth_pct),
            depth_p99_pct: percentile(&mut self.depth_pct.clone(), 99.0),
            colour_worst_step: self.steps.iter().copied().fold(0.0, f64::max),
            colour_jump: jump(&self.steps),
            depth_jump_pct: jump(&self.depth_steps),
        }
    }
}

/// The largest excess of one step over the mean of the two steps on either side of it,
/// 0 when no step stands out (and with fewer than three steps). A level switched at once
/// puts its whole change into one step; what neighbouring steps share (the floor of
/// re-sampled edges, an error that grows steadily as the camera nears the surface) is
/// taken off.
fn jump(steps: &[f64]) -> f64 {
    steps
        .windows(3)
        .map(|w| w[1] - (w[0] + w[2]) / 2.0)
        .fold(0.0, f64::max)
}

/// Frame-to-frame change beyond the reference's (see the module docs).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Popping {
    /// Colour, 0 to 255 per channel: mean and 99th percentile.
    pub colour_mean: f64,
    pub colour_p99: f64,
    /// Depth, percent of the distance: mean and 99th percentile.
    pub depth_mean_pct: f64,
    pub depth_p99_pct: f64,
    /// The largest mean colour change of one step: a level switched at once puts its whole
    /// change into one step, a morph spreads it over many (the means above, sums over every
    /// step, cannot tell the two apart).
    pub colour_worst_step: f64,
    /// The largest step's excess over its neighbours' mean, colour (0 to 255) and depth
    /// (percent): one switch stands out, a morph's change and the drift every step shares
    /// do not.
    pub colour_jump: f64,
    pub depth_jump_pct: f64,
}

#[cfg(test)]
mod tests {
    use super::*;

    fn capture(colour: [u8; 3], distance: Option<f64>) -> Capture {
        let (w, h) = (10, 10);
        Capture {
            color: image::RgbaImage::from_pixel(
                w,
                h,
                image::Rgba([colour[0], colour[1], colour[2], 255]),
            ),
            depth: vec![0.5; (w * h) as usize],
            points: vec![distance.map(|d| [d, 0.0, 0.0]); (w * h) as usize],
        }
    }

    fn pair<'a>(method: &'a Capture, reference: &'a Capture, eye: [f64; 3]) -> Pair<'a> {
        Pair {
            method,
            reference,
            eye,
        }
    }

    #[test]
    fn the_same_frame_twice_does_not_pop() {
        let frame = capture([10, 200, 30], Some(100.0));
        let mut changes = Changes::default();
        changes.add(
            pair(&frame, &frame, [0.0; 3]),
            pair(&frame, &frame, [0.0; 3]),
        );
        assert_eq!(changes.summary(), Popping::default());
    }

    #[test]
    fn a_method_that_changes_as_the_reference_does_does_not_pop() {
        // The camera moves 5 m towards the surface; both see it come nearer, and the
        // method's frames are off the reference's by a constant colour.
        let (ra, rb) = (
            capture([10, 10, 10], Some(100.0)),
            capture([20, 10, 10], Some(100.0)),
        );
        let (ma, mb) = (
            capture([12, 10, 10], Some(100.0)),
            capture([22, 10, 10], Some(100.0)),
        );
        let mut changes = Changes::default();
        changes.add(pair(&ma, &ra, [0.0; 3]), pair(&mb, &rb, [5.0, 0.0, 0.0]));
        assert_eq!(changes.summary(), Popping::default());
    }

    #[test]
    fn a_jump_the_reference_does_not_make_is_measured() {
        let reference = capture([10, 10, 10], Some(100.0));
        let (ma, mb) = (
            capture([10, 10, 10], Some(100.0)),
            capture([16, 10, 13], Some(110.0)),
        );
        let mut changes = Changes::default();
        changes.add(
            pair(&ma, &reference, [0.0; 3]),
            pair(&mb, &reference, [0.0; 3]),
        );
        let popping = changes.summary();
        assert_eq!((popping.colour_mean, popping.colour_p99), (3.0, 3.0));
        assert!((popping.depth_mean_pct - 10.0).abs() < 1e-12);
        // Background in one frame: no depth change counted there.
        let sky = capture([0, 0, 0], None);
        let mut changes = Changes::default();
        changes.add(
            pair(&sky, &reference, [0.0; 3]),
            pair(&mb, &reference, [0.0; 3]),
        );
        assert_eq!(changes.summary().depth_mean_pct, 0.0);
    }

    #[test]
    fn a_change_spread_over_steps_has_the_same_mean_but_a_smaller_worst_step() {
        let reference = capture([10, 10, 10], Some(100.0));
        let frames: Vec<Capture> = [10, 40, 40, 40]
            .iter()
            .map(|&c| capture([c, 10, 10], Some(100.0)))
            .collect();
        let morphed: Vec<Capture> = [10, 20, 30, 40]
            .iter()
            .map(|&c| capture([c, 10, 10], Some(100.0)))
            .collect();
        let run = |frames: &[Capture]| {
            let mut changes = Changes::default();
            for k in 1..frames.len() {
                changes.add(
                    pair(&frames[k - 1], &reference, [0.0; 3]),
                    pair(&frames[k], &reference, [0.0; 3]),
                );
            }
            changes.summary()
        };
        let (at_once, spread) = (run(&frames), run(&morphed));
        assert!((at_once.colour_mean - spread.colour_mean).abs() < 1e-12);
        assert_eq!(at_once.colour_worst_step, 10.0);
        assert!((spread.colour_worst_step - 10.0 / 3.0).abs() < 1e-12);
        // Two steps on either side of the switch.
        let frames: Vec<Capture> = [10, 10, 10, 40, 40, 40]
            .iter()
            .map(|&c| capture([c, 10, 10], Some(100.0)))
            .collect();
        let morphed: Vec<Capture> = [10, 16, 22, 28, 34, 40]
            .iter()
            .map(|&c| capture([c, 10, 10], Some(100.0)))
            .collect();
        let (at_once, spread) = (run(&frames), run(&morphed));
        assert_eq!(at_once.colour_jump, 10.0);
        assert!(spread.colour_jump.abs() < 1e-12);
    }

    #[test]
    fn a_jump_stands_out_of_a_drift_that_every_step_shares() {
        // Steps of a frame whose error grows as the camera nears (1, 2, 3, ...), with one
        // level switch adding 5 at the fourth step.
        let steps = [1.0, 2.0, 3.0, 9.0, 5.0, 6.0];
        assert!((jump(&steps) - 5.0).abs() < 1e-12);
        assert_eq!(jump(&[1.0, 2.0, 3.0, 4.0]), 0.0);
        assert_eq!(jump(&[2.0, 2.0, 2.0]), 0.0);
        assert_eq!(jump(&[4.0, 1.0]), 0.0);
        assert_eq!(jump(&[3.0]), 0.0);
        assert_eq!(jump(&[]), 0.0);
    }
}
