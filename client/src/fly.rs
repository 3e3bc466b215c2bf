//! A free-flying camera steered by a user: what the window ([`crate::viewer`]) and the
//! browser page (`web/`) fly with. Pure: values in, values out.

use crate::render::Camera;
use std::f64::consts::TAU;
use terrain_shared::Manifest;

/// Steepest pitch the camera takes, degrees above or below the horizon.
pub const MAX_PITCH_DEG: f64 = 89.0;
/// Speed factor while Shift is held.
pub const FAST_FACTOR: f64 = 5.0;
/// Speed factor per notch of the mouse wheel.
pub const WHEEL_FACTOR: f64 = 1.25;
/// Radians the view turns per pixel of mouse drag.
pub const LOOK_RADIANS_PER_PIXEL: f64 = 0.003;
/// Metres the camera keeps above the ground under it (where that tile is resident; the
/// terrain's lowest point elsewhere).
pub const GROUND_CLEARANCE_M: f64 = 2.0;
/// Longest time step a frame moves the camera by: after a stall (a window drag, a slow
/// frame) the camera does not jump.
pub const MAX_STEP_S: f64 = 0.25;
/// Slowest and fastest speeds the wheel can set, m/s.
pub const SPEED_RANGE: (f64, f64) = (0.1, 1.0e7);
/// The camera stays within this many metres of the origin on each axis.
pub const POSITION_LIMIT_M: f64 = 1.0e9;

/// Parses `X,Y,Z` (metres, finite).
pub fn parse_point(text: &str) -> Result<[f64; 3], String> {
    let parts: Vec<&str> = text.split(',').map(str::trim).collect();
    let [x, y, z] = parts.as_slice() else {
        return Err(format!(
            "{text:?}: expected X,Y,Z in metres, e.g. 1000,2000,800"
        ));
    };
    let parse = |v: &str| {
        v.parse::<f64>()
            .ok()
            .filter(|n| n.is_finite())
            .ok_or_else(|| format!("{text:?}: {v:?} is not a finite number of metres"))
    };
    Ok([parse(x)?, parse(y)?, parse(z)?])
}

/// Where the camera starts by default: above the terrain's centre, 5% of its larger extent
/// above its highest point (the height of [`crate::path::CameraPath::default_for`]).
pub fn default_start(manifest: &Manifest) -> [f64; 3] {
    let [w, h] = manifest.extent_m;
    [w / 2.0, h / 2.0, manifest.heights.max_m + 0.05 * w.max(h)]
}

/// The default speed: a tenth of the terrain's larger extent per second.
pub fn default_speed(manifest: &Manifest) -> f64 {
    let [w, h] = manifest.extent_m;
    (0.1 * w.max(h)).clamp(SPEED_RANGE.0, SPEED_RANGE.1)
}

/// What the user asks of the camera over one frame.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct FlyInput {
    /// +1 forward, -1 back.
    pub forward: f64,
    /// +1 right, -1 left.
    pub right: f64,
    /// +1 up, -1 down.
    pub up: f64,
    /// Shift held: [`FAST_FACTOR`] times faster.
    pub fast: bool,
    /// Mouse drag since the last frame, pixels (right, down).
    pub look: [f64; 2],
    /// Mouse wheel notches since the last frame (positive: faster).
    pub wheel: f64,
}

/// A free-flying camera: position, heading and speed. Pure: [`FlyCamera::apply`] moves it
/// by an input over a time step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FlyCamera {
    /// Metres, x east, y south, z up.
    pub position: [f64; 3],
    /// Radians: 0 looks east, pi/2 south.
    pub yaw: f64,
    /// Radians above the horizon, within ±[`MAX_PITCH_DEG`].
    pub pitch: f64,
    /// Metres per second without Shift.
    pub speed: f64,
}

impl FlyCamera {
    pub fn new(position: [f64; 3], yaw: f64, pitch: f64, speed: f64) -> FlyCamera {
        let max = MAX_PITCH_DEG.to_radians();
        FlyCamera {
            position,
            yaw: if yaw.is_finite() {
                yaw.rem_euclid(TAU)
            } else {
                0.0
            },
            pitch: if pitch.is_finite() {
                pitch.clamp(-max, max)
            } else {
                0.0
            },
            speed: if speed.is_finite() {
                speed.clamp(SPEED_RANGE.0, SPEED_RANGE.1)
            } else {
                SPEED_RANGE.0
            },
        }
    }

    /// Unit view direction (east, south, up).
    pub fn direction(&self) -> [f64; 3] {
        [
            self.pitch.cos() * self.yaw.cos(),
            self.pitch.cos() * self.yaw.sin(),
            self.pitch.sin(),
        ]
    }

    /// Unit horizontal direction to the right of the view.
    pub fn right(&self) -> [f64; 3] {
        [-self.yaw.sin(), self.yaw.cos(), 0.0]
    }

    /// Applies `input` over `dt` seconds (clamped to [0, [`MAX_STEP_S`]]): the wheel sets
    /// the speed, the drag turns the view (pitch clamped), then the camera moves forward
    /// along the view, sideways horizontally and up vertically. A step that would leave the
    /// position non-finite is not taken.
    pub fn apply(&mut self, input: &FlyInput, dt: f64) {
        let dt = if dt.is_finite() {
            dt.clamp(0.0, MAX_STEP_S)
        } else {
            0.0
        };
        if input.wheel.is_finite() {
            self.speed =
                (self.speed * WHEEL_FACTOR.powf(input.wheel)).clamp(SPEED_RANGE.0, SPEED_RANGE.1);
        }
        let [dx, dy] = input.look;
        if dx.is_finite() && dy.is_finite() {
            let max = MAX_PITCH_DEG.to_radians();
            self.yaw = (self.yaw + dx * LOOK_RADIANS_PER_PIXEL).rem_euclid(TAU);
            self.pitch = (self.pitch - dy * LOOK_RADIANS_PER_PIXEL).clamp(-max, max);
        }
        let speed = self.speed * if input.fast { FAST_FACTOR } else { 1.0 };
        let step = speed * dt;
        let (f, r, u) = (
            input.forward.clamp(-1.0, 1.0),
            input.right.clamp(-1.0, 1.0),
            input.up.clamp(-1.0, 1.0),
        );
        let forward = self.direction();
        let right = self.right();
        let next: [f64; 3] = std::array::from_fn(|i| {
            let vertical = if i == 2 { u } else { 0.0 };
            self.position[i] + step * (f * forward[i] + r * right[i] + vertical)
        });
        if next.iter().all(|v| v.is_finite()) {
            self.position = next.map(|v| v.clamp(-POSITION_LIMIT_M, POSITION_LIMIT_M));
        }
    }

    /// Lifts the camera to [`GROUND_CLEARANCE_M`] above `ground` (metres) when below it.
    pub fn keep_above(&mut self, ground: Option<f64>) {
        if let Some(g) = ground.filter(|g| g.is_finite()) {
            self.position[2] = self.position[2].max(g + GROUND_CLEARANCE_M);
        }
    }

    /// The renderer's camera.
    pub fn camera(&self) -> Camera {
        Camera::new(self.position, self.yaw, self.pitch)
    }
}
