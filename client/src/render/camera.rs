//! The camera: where it is, where it looks, and the frustum it sees.
//!
//! World coordinates are the terrain's: x east and y south from raster sample (0, 0),
//! z up, in metres (f64). Rendering happens in camera-relative *render space*, x east, y up,
//! z south, with the camera at the origin, so `f32` positions stay precise on terrains
//! thousands of kilometres wide. The projection has reversed depth (near at 1, an infinite
//! far plane at 0), which keeps `Depth32Float` precise from a metre to the horizon.

use glam::{DMat4, DVec3, DVec4, Mat4};

/// Vertical field of view by default, degrees.
pub const DEFAULT_FOV_Y_DEG: f64 = 55.0;
/// Pitch of the default flight camera below the horizon, degrees.
pub const DEFAULT_PITCH_DEG: f64 = -25.0;

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera {
    /// World position, metres (x east, y south, z up).
    pub position: [f64; 3],
    /// Heading, radians: 0 looks east, pi/2 looks south.
    pub yaw: f64,
    /// Radians above the horizon (negative looks down).
    pub pitch: f64,
    /// Vertical field of view, radians.
    pub fov_y: f64,
    /// Distance of the near plane, metres.
    pub near: f64,
}

impl Camera {
    /// A camera at `position` looking along `yaw` and `pitch` (radians), default field of
    /// view, and a near plane at 1 m.
    pub fn new(position: [f64; 3], yaw: f64, pitch: f64) -> Camera {
        Camera {
            position,
            yaw,
            pitch,
            fov_y: DEFAULT_FOV_Y_DEG.to_radians(),
            near: 1.0,
        }
    }

    /// A camera at `position` looking at `target` (world coordinates).
    pub fn looking_at(position: [f64; 3], target: [f64; 3]) -> Camera {
        let d = DVec3::from(target) - DVec3::from(position);
        let yaw = d.y.atan2(d.x);
        let pitch = d.z.atan2(d.truncate().length());
        Camera::new(position, yaw, pitch)
    }

    /// Unit view direction in world coordinates.
    pub fn direction(&self) -> DVec3 {
        DVec3::new(
            self.pitch.cos() * self.yaw.cos(),
            self.pitch.cos() * self.yaw.sin(),
            self.pitch.sin(),
        )
    }

    /// World-to-render-space direction: (east, south, up) to (east, up, south).
    pub fn to_render(v: DVec3) -> DVec3 {
        DVec3::new(v.x, v.z, v.y)
    }

    /// View-projection from camera-relative render space to clip space, for a target of
    /// `aspect` = width / height.
    pub fn view_proj(&self, aspect: f64) -> DMat4 {
        let forward = Self::to_render(self.direction());
        // Straight up or down has no horizontal heading: take the heading as "up" then.
        let up = if forward.y.abs() > 0.999_999 {
            Self::to_render(DVec3::new(self.yaw.cos(), self.yaw.sin(), 0.0))
        } else {
            DVec3::Y
        };
        let view = glam::dcamera::rh::view::look_to_mat4(DVec3::ZERO, forward, up);
        // WebGPU's convention: depth in [0, 1], y up.
        let proj = glam::dcamera::rh::proj::directx::perspective_infinite_reverse(
            self.fov_y, aspect, self.near,
        );
        proj * view
    }

    /// [`Camera::view_proj`] in `f32`, for the shader.
    pub fn view_proj_f32(&self, aspect: f64) -> Mat4 {
        self.view_proj(aspect).as_mat4()
    }

    /// The frustum for a target of `aspect`.
    pub fn frustum(&self, aspect: f64) -> Frustum {
        Frustum::from_view_proj(&self.view_proj(aspect))
    }
}

/// The planes bounding what a camera sees (left, right, bottom, top, near; the far plane is
/// at infinity), in camera-relative render space, each `a x + b y + c z + d >= 0` inside.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Frustum {
    planes: [DVec4; 5],
}

impl Frustum {
    /// Planes of a view-projection matrix (Gribb and Hartmann), depth in [0, 1] reversed.
    pub fn from_view_proj(m: &DMat4) -> Frustum {
        let row = |i: usize| m.row(i);
        let (r0, r1, r2, r3) = (row(0), row(1), row(2), row(3));
        let planes = [r3 + r0, r3 - r0, r3 + r1, r3 - r1, r3 - r2];
        Frustum {
            planes: planes.map(|p| p / p.truncate().length().max(f64::MIN_POSITIVE)),
        }
    }

    /// Whether the box from `min` to `max` (render space, camera-relative) may be visible:
    /// false only when it lies wholly outside one plane.
    pub fn intersects_box(&self, min: DVec3, max: DVec3) -> bool {
        self.planes.iter().all(|p| {
            // The box corner farthest along the plane's normal.
            let corner = DVec3::new(
                if p.x >= 0.0 { max.x } else { min.x },
                if p.y >= 0.0 { max.y } else { min.y },
                if p.z >= 0.0 { max.z } else { min.z },
            );
            p.truncate().dot(corner) + p.w >= 0.0
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn looking_at_points_the_view_at_the_target() {
        let camera = Camera::looking_at([0.0, 0.0, 100.0], [100.0, 100.0, 0.0]);
        let d = camera.direction();
        let expected = DVec3::new(1.0, 1.0, -1.0).normalize();
        assert!((d - expected).length() < 1e-12, "{d:?}");
    }

    #[test]
    fn the_target_projects_to_the_centre_of_the_screen_in_front_of_the_camera() {
        let camera = Camera::looking_at([10.0, 20.0, 300.0], [500.0, 700.0, 50.0]);
        let m = camera.view_proj(16.0 / 9.0);
        let relative = Camera::to_render(DVec3::new(490.0, 680.0, -250.0));
        let clip = m * relative.extend(1.0);
        let ndc = clip.truncate() / clip.w;
        assert!(ndc.x.abs() < 1e-9 && ndc.y.abs() < 1e-9, "{ndc:?}");
        assert!(
            ndc.z > 0.0 && ndc.z < 1.0,
            "reversed depth in (0, 1): {ndc:?}"
        );
        // Ground beyond the target, along the view, appears higher on screen.
        let farther = Camera::to_render(DVec3::new(590.0, 780.0, -250.0));
        let clip2 = m * farther.extend(1.0);
        assert!(
            clip2.y / clip2.w > 0.0,
            "farther ground appears higher on screen"
        );
        assert!(
            clip2.z / clip2.w < ndc.z,
            "farther is deeper (smaller reversed depth)"
        );
    }

    #[test]
    fn the_frustum_keeps_what_is_in_front_and_culls_what_is_behind_or_beside() {
        let camera = Camera::new([0.0, 0.0, 0.0], 0.0, 0.0); // looks east
        let frustum = camera.frustum(1.0);
        let at = |east: f64, up: f64, south: f64| {
            let c = DVec3::new(east, up, south);
            frustum.intersects_box(c - 1.0, c + 1.0)
        };
        assert!(at(100.0, 0.0, 0.0), "ahead");
        assert!(!at(-100.0, 0.0, 0.0), "behind");
        assert!(!at(100.0, 0.0, 300.0), "far to the right");
        assert!(!at(100.0, 300.0, 0.0), "far above");
        assert!(at(1.0e7, 0.0, 0.0), "no far plane");
        // A huge box around the camera is always visible.
        assert!(frustum.intersects_box(DVec3::splat(-1e4), DVec3::splat(1e4)));
    }
}
