//! Popping: how much a method's frame changes from the one before while the camera moves a
//! little, beyond what the reference's own frames change between the same cameras.
//!
//! A level of detail that switches a tile from one mask to another makes the surface jump
//! between two frames; a camera moving a few metres a frame changes the reference only a
//! little. Per pixel and per pair of consecutive frames:
//!
//! - the **colour change** is the mean absolute difference of the red, green and blue
//!   channels (0 to 255), over every pixel;
//! - the **depth change** is the change of the distance from the camera to the surface the
//!   pixel shows, in percent of the nearer of the two, over pixels showing terrain in both.
//!
//! A method's popping is its mean and 99th percentile of each, minus the reference's mean
//! and 99th percentile over the same cameras. A still camera gives zero. Pure: captures in,
//! numbers out.

use super::frame::Capture;
use super::metrics::percentile;

/// Changes between consecutive frames, per pixel, gathered over a run of frames.
#[derive(Debug, Clone, Default)]
pub struct Changes {
    colour: Vec<f64>,
    depth_pct: Vec<f64>,
}

impl Changes {
    /// Adds the changes from frame `a` (seen from `eye_a`) to frame `b` (from `eye_b`).
    pub fn add(&mut self, a: &Capture, eye_a: [f64; 3], b: &Capture, eye_b: [f64; 3]) {
        for (pa, pb) in a.color.pixels().zip(b.color.pixels()) {
            let sum: u32 = (0..3).map(|k| u32::from(pa[k].abs_diff(pb[k]))).sum();
            self.colour.push(f64::from(sum) / 3.0);
        }
        let distance = |p: [f64; 3], eye: [f64; 3]| {
            ((p[0] - eye[0]).powi(2) + (p[1] - eye[1]).powi(2) + (p[2] - eye[2]).powi(2)).sqrt()
        };
        for (pa, pb) in a.points.iter().zip(&b.points) {
            if let (Some(pa), Some(pb)) = (pa, pb) {
                let (da, db) = (distance(*pa, eye_a), distance(*pb, eye_b));
                let nearer = da.min(db);
                if nearer > 0.0 {
                    self.depth_pct.push(100.0 * (da - db).abs() / nearer);
                }
            }
        }
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
        }
    }
}

/// Frame-to-frame change (see the module docs): as measured for one run, or, from
/// [`Popping::beyond`], what a method adds to the reference's.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Popping {
    /// Colour change, 0 to 255 per channel: mean and 99th percentile.
    pub colour_mean: f64,
    pub colour_p99: f64,
    /// Depth change, percent of the distance: mean and 99th percentile.
    pub depth_mean_pct: f64,
    pub depth_p99_pct: f64,
}

impl Popping {
    /// This run's change minus `reference`'s, statistic by statistic.
    pub fn beyond(self, reference: Popping) -> Popping {
        Popping {
            colour_mean: self.colour_mean - reference.colour_mean,
            colour_p99: self.colour_p99 - reference.colour_p99,
            depth_mean_pct: self.depth_mean_pct - reference.depth_mean_pct,
            depth_p99_pct: self.depth_p99_pct - reference.depth_p99_pct,
        }
    }
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

    #[test]
    fn the_same_frame_twice_does_not_pop() {
        let frame = capture([10, 200, 30], Some(100.0));
        let mut changes = Changes::default();
        changes.add(&frame, [0.0; 3], &frame, [0.0; 3]);
        assert_eq!(changes.summary(), Popping::default());
    }

    #[test]
    fn a_known_change_is_measured_and_the_references_own_is_taken_off() {
        let mut method = Changes::default();
        method.add(
            &capture([10, 10, 10], Some(100.0)),
            [0.0; 3],
            &capture([16, 10, 13], Some(110.0)),
            [0.0; 3],
        );
        let popping = method.summary();
        assert_eq!(popping.colour_mean, 3.0);
        assert_eq!(popping.colour_p99, 3.0);
        assert!((popping.depth_mean_pct - 10.0).abs() < 1e-12);
        // The camera moved 5 m towards the surface: the reference's own change.
        let mut reference = Changes::default();
        reference.add(
            &capture([10, 10, 10], Some(100.0)),
            [0.0; 3],
            &capture([10, 10, 10], Some(100.0)),
            [5.0, 0.0, 0.0],
        );
        let beyond = popping.beyond(reference.summary());
        assert!((beyond.depth_mean_pct - (10.0 - 100.0 * 5.0 / 95.0)).abs() < 1e-9);
        assert_eq!(beyond.colour_mean, 3.0);
        // Background in one frame: no depth change counted there.
        let mut sky = Changes::default();
        sky.add(
            &capture([0, 0, 0], None),
            [0.0; 3],
            &capture([0, 0, 0], Some(50.0)),
            [0.0; 3],
        );
        assert_eq!(sky.summary().depth_mean_pct, 0.0);
    }
}
