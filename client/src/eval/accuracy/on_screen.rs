//! Which samples of a tile can show on screen, for the oracle that frees the others
//! (`bench accuracy --on-screen-oracle`).

use crate::render::Camera;
use crate::render::camera::Frustum;

/// Per sample of a tile (row-major), whether a cell it is a corner of can show on screen:
/// the box of the cells around it (one sample each way, within the tile; from the lowest
/// to the highest of their samples) meets `frustum`. Any surface drawn over a cell lies in
/// that box, so a sample whose box is out of view constrains nothing a frame shows.
pub(super) fn samples_in_view(
    frustum: &Frustum,
    eye: glam::DVec3,
    origin: [f64; 2],
    spacing: [f64; 2],
    samples: &[f32],
    n: u32,
) -> Vec<bool> {
    let last = n - 1;
    let mut out = Vec::with_capacity(samples.len());
    for r in 0..n {
        for c in 0..n {
            let (c0, c1) = (c.saturating_sub(1), (c + 1).min(last));
            let (r0, r1) = (r.saturating_sub(1), (r + 1).min(last));
            let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
            for rr in r0..=r1 {
                for &h in &samples[(rr * n + c0) as usize..=(rr * n + c1) as usize] {
                    lo = lo.min(h);
                    hi = hi.max(h);
                }
            }
            let at = |c: u32, r: u32, h: f32| {
                Camera::to_render(
                    glam::DVec3::new(
                        origin[0] + f64::from(c) * spacing[0],
                        origin[1] + f64::from(r) * spacing[1],
                        f64::from(h),
                    ) - eye,
                )
            };
            let (a, b) = (at(c0, r0, lo), at(c1, r1, hi));
            out.push(frustum.intersects_box(a.min(b), a.max(b)));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn samples_behind_the_camera_are_off_screen_and_those_ahead_on_it() {
        // Looking east from x = 0: a tile ahead (x 1000..1160) shows, one behind does not;
        // a tile reaching across the view's side shows only on the inner side.
        let camera = Camera::looking_at([0.0, 0.0, 100.0], [1000.0, 0.0, 0.0]);
        let frustum = camera.frustum(16.0 / 9.0);
        let eye = glam::DVec3::from(camera.position);
        let n = 17;
        let flat = vec![0.0f32; (n * n) as usize];
        let seen =
            |origin: [f64; 2]| samples_in_view(&frustum, eye, origin, [10.0, 10.0], &flat, n);
        assert!(seen([1000.0, -80.0]).iter().all(|&v| v));
        assert!(seen([-1160.0, -80.0]).iter().all(|&v| !v));
        let across = seen([300.0, 200.0]);
        assert!(across.iter().any(|&v| v) && across.iter().any(|&v| !v));
    }
}
