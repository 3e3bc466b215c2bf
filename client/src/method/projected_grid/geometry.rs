//! The pure geometry of the projected grids ([`crate::method::projected_grid`]): the
//! auxiliary camera the grid is cast from, and the warp that makes the cast grid's cells
//! square.
//!
//! Angles here are measured below the horizon (positive looks down), in radians. Vectors
//! are in render space: x east, y up, z south, camera at the origin.

use crate::render::Camera;
use glam::DVec3;

/// Livny et al.'s `epsilon` of equation 2: how far below the horizon the auxiliary
/// camera's top row looks when it is restricted, radians. Their epsilon tends to 0; a
/// tenth of a degree keeps the top row's rays meeting the plane within a few hundred
/// kilometres of a camera a few hundred metres above it.
pub const AUX_EPSILON_RAD: f64 = 0.1 * std::f64::consts::PI / 180.0;
/// The auxiliary camera's field of view when it is restricted: at least 90 degrees, so it
/// sees from the ground below the viewpoint to the horizon (Livny et al., section 3.2).
pub const AUX_MIN_FOV_RAD: f64 = std::f64::consts::FRAC_PI_2;

/// Cells per side of the coarse grid the warp is computed on (Löffler et al.: a coarse
/// grid warped on the CPU, refined on the GPU); its tables have one more line.
pub const WARP_CELLS: usize = terrain_shaders::WARP_LINES - 1;
/// Share of the warped grid's lines spread uniformly whatever the importance, so no part of
/// the screen is left without lines.
pub const WARP_UNIFORM_SHARE: f64 = 0.25;
/// Largest ratio of importance between two parts of the grid.
pub const WARP_MAX_RATIO: f64 = 8.0;

/// The camera a projected grid is cast from: its axes and the tangents of its half fields
/// of view.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AuxCamera {
    pub forward: DVec3,
    pub right: DVec3,
    pub up: DVec3,
    pub tan_x: f64,
    pub tan_y: f64,
    /// Whether it differs from the main camera (equation 2 restricted it, or it reaches
    /// further down for peaks beside the view).
    pub restricted: bool,
}

impl AuxCamera {
    /// The camera at the main camera's place looking `pitch` radians above the horizon
    /// along `yaw`, with these half-field tangents.
    pub fn looking(yaw: f64, pitch: f64, tan_x: f64, tan_y: f64, restricted: bool) -> AuxCamera {
        let forward = DVec3::new(
            pitch.cos() * yaw.cos(),
            pitch.sin(),
            pitch.cos() * yaw.sin(),
        );
        let right = DVec3::new(-yaw.sin(), 0.0, yaw.cos());
        AuxCamera {
            forward,
            right,
            up: right.cross(forward),
            tan_x,
            tan_y,
            restricted,
        }
    }

    /// The unit ray through auxiliary screen point `uv` (`[0, 1]^2` from the top left).
    pub fn ray(&self, uv: [f64; 2]) -> DVec3 {
        let x = uv[0] * 2.0 - 1.0;
        let y = 1.0 - uv[1] * 2.0;
        (self.forward + x * self.tan_x * self.right + y * self.tan_y * self.up).normalize()
    }

    /// Where the ray through `uv` meets the plane `plane_y` below the camera (render
    /// space), or its point at `far_m` when it meets it farther or not at all: what the
    /// shader's `ground_of` computes.
    pub fn ground(&self, uv: [f64; 2], plane_y: f64, far_m: f64) -> DVec3 {
        let d = self.ray(uv);
        let t = if d.y < -1e-7 {
            (plane_y / d.y).min(far_m)
        } else {
            far_m
        };
        DVec3::new(d.x * t, plane_y, d.z * t)
    }
}

/// The auxiliary camera for `main` on a target of `aspect`, the camera `above_plane_m`
/// above the plane the grid is cast onto and `clearance_m` above the terrain's highest
/// point (negative when below it).
///
/// - Livny et al.'s equation 2: `A_aux = max(A_main, FOV/2 + epsilon)`, with the field of
///   view widened to 90 degrees when it applies, so no ray runs parallel to the plane or
///   away from it, and the ground from below the viewpoint to the horizon is sampled.
/// - Johanson's and Löffler et al.'s case of high amplitude (their figure 2b): a peak
///   whose foot lies below the bottom of the view can still rise into it; the bottom row
///   reaches down to the foot of the nearest point the main camera's bottom rays can see at
///   the highest height.
pub fn aux_camera(main: &Camera, aspect: f64, above_plane_m: f64, clearance_m: f64) -> AuxCamera {
    let half = main.fov_y / 2.0;
    let tan_y_main = half.tan();
    let tan_x_main = tan_y_main * aspect;
    let centre = -main.pitch;
    let (mut top, mut bottom) = (centre - half, centre + half);
    let mut restricted = false;
    if top < AUX_EPSILON_RAD {
        let fov = main.fov_y.max(AUX_MIN_FOV_RAD);
        let a_aux = centre.max(fov / 2.0 + AUX_EPSILON_RAD);
        top = a_aux - fov / 2.0;
        bottom = (a_aux + fov / 2.0).min(std::f64::consts::FRAC_PI_2);
        restricted = true;
    }
    // The foot of the nearest point at the highest height the main camera's bottom row
    // sees: at clearance / tan(bottom of main) horizontally.
    let main_bottom = centre + half;
    let needed = if clearance_m <= 0.0 || main_bottom >= std::f64::consts::FRAC_PI_2 {
        std::f64::consts::FRAC_PI_2
    } else {
        (above_plane_m.max(0.0) * main_bottom.tan() / clearance_m).atan()
    };
    if needed > bottom + 1e-12 {
        bottom = needed.min(std::f64::consts::FRAC_PI_2).max(bottom);
        restricted = true;
    }
    let half_aux = (bottom - top) / 2.0;
    let tan_y = half_aux.tan();
    // A row off the auxiliary axis spans a narrower angle across than the same tangent on
    // the axis: widen so that every row the main camera sees is covered across.
    let tan_x = if restricted {
        tan_x_main * (1.0 + tan_y * tan_y).sqrt()
    } else {
        tan_x_main
    };
    AuxCamera::looking(main.yaw, -(top + bottom) / 2.0, tan_x, tan_y, restricted)
}

/// Löffler et al.'s view-dependent grid: the uniform coarse grid is cast onto the plane,
/// each cell's aspect ratio (across over along the view) measured, and the grid lines
/// moved so that rows crowd where cells are long along the view and columns where they are
/// wide across it: cast, the cells come out closer to square. Importance-driven warping
/// (Dachsbacher and Stamminger) done separably, rows and columns each by the inverse of
/// the cumulative importance. Returns where each of the tables' lines sits across (`u`)
/// and down (`v`) the auxiliary screen, in `[0, 1]`, first 0 and last 1.
// Cells are indexed by row and column at once (both sums grow in the same loop).
#[allow(clippy::needless_range_loop)]
pub fn warp_tables(
    aux: &AuxCamera,
    plane_y: f64,
    far_m: f64,
) -> ([f64; WARP_CELLS + 1], [f64; WARP_CELLS + 1]) {
    let k = WARP_CELLS;
    let ground: Vec<DVec3> = (0..=k)
        .flat_map(|j| (0..=k).map(move |i| (i, j)))
        .map(|(i, j)| aux.ground([i as f64 / k as f64, j as f64 / k as f64], plane_y, far_m))
        .collect();
    let at = |i: usize, j: usize| ground[j * (k + 1) + i];
    let mut rows = vec![0.0; k];
    let mut columns = vec![0.0; k];
    for j in 0..k {
        for i in 0..k {
            let along = 0.5
                * ((at(i, j + 1) - at(i, j)).length() + (at(i + 1, j + 1) - at(i + 1, j)).length());
            let across = 0.5
                * ((at(i + 1, j) - at(i, j)).length() + (at(i + 1, j + 1) - at(i, j + 1)).length());
            let ratio = if across > 0.0 && along > 0.0 {
                (along / across).clamp(1.0 / WARP_MAX_RATIO, WARP_MAX_RATIO)
            } else {
                1.0
            };
            rows[j] += ratio / k as f64;
            columns[i] += 1.0 / ratio / k as f64;
        }
    }
    (inverse_cdf(&columns), inverse_cdf(&rows))
}

/// Where lines `0..=n` sit when spread by `density` (one value per uniform cell):
/// the inverse of its cumulative sum, mixed with a uniform spread.
fn inverse_cdf(density: &[f64]) -> [f64; WARP_CELLS + 1] {
    let k = density.len();
    let mean = density.iter().sum::<f64>() / k as f64;
    let weights: Vec<f64> = density
        .iter()
        .map(|&d| {
            let d = if mean > 0.0 && d.is_finite() {
                d / mean
            } else {
                1.0
            };
            WARP_UNIFORM_SHARE + (1.0 - WARP_UNIFORM_SHARE) * d
        })
        .collect();
    let mut cumulative = vec![0.0; k + 1];
    for c in 0..k {
        cumulative[c + 1] = cumulative[c] + weights[c];
    }
    let total = cumulative[k];
    let mut out = [0.0; WARP_CELLS + 1];
    let mut c = 0;
    for (line, slot) in out.iter_mut().enumerate() {
        let target = total * line as f64 / WARP_CELLS as f64;
        while c + 1 < k && cumulative[c + 1] < target {
            c += 1;
        }
        let span = weights[c].max(f64::MIN_POSITIVE);
        let within = ((target - cumulative[c]) / span).clamp(0.0, 1.0);
        *slot = ((c as f64 + within) / k as f64).clamp(0.0, 1.0);
    }
    out[0] = 0.0;
    out[WARP_CELLS] = 1.0;
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera(pitch_deg: f64) -> Camera {
        Camera::new([0.0, 0.0, 500.0], 0.3, pitch_deg.to_radians())
    }

    /// The angle below the horizon of the auxiliary camera's top and bottom rows.
    fn rows(aux: &AuxCamera) -> (f64, f64) {
        let below = |uv: [f64; 2]| -aux.ray(uv).y.asin();
        (below([0.5, 0.0]), below([0.5, 1.0]))
    }

    #[test]
    fn looking_well_down_over_flat_ground_the_auxiliary_camera_is_the_main_one() {
        let main = camera(-60.0);
        // The plane is the ground: nothing rises above it.
        let aux = aux_camera(&main, 16.0 / 9.0, 500.0, 500.0);
        assert!(!aux.restricted);
        let d = Camera::to_render(main.direction());
        assert!(
            (aux.forward - d).length() < 1e-12,
            "{:?} vs {d:?}",
            aux.forward
        );
        assert!((aux.tan_y - (main.fov_y / 2.0).tan()).abs() < 1e-12);
    }

    #[test]
    fn at_or_above_the_horizon_every_ray_meets_the_plane_from_below_the_viewpoint_to_the_horizon() {
        for pitch in [-20.0, 0.0, 30.0, 89.0] {
            let aux = aux_camera(&camera(pitch), 16.0 / 9.0, 500.0, 100.0);
            assert!(aux.restricted, "pitch {pitch}");
            let (top, bottom) = rows(&aux);
            assert!(
                (top - AUX_EPSILON_RAD).abs() < 1e-9,
                "pitch {pitch}: top row {top} rad below the horizon"
            );
            assert!(
                (bottom - std::f64::consts::FRAC_PI_2).abs() < 1e-9,
                "pitch {pitch}: bottom row {bottom}"
            );
            for j in 0..=10 {
                for i in 0..=10 {
                    let d = aux.ray([i as f64 / 10.0, j as f64 / 10.0]);
                    assert!(d.y < 0.0, "pitch {pitch}: a ray runs level or up: {d:?}");
                }
            }
        }
    }

    #[test]
    fn low_over_a_peak_the_bottom_row_reaches_the_ground_below_the_viewpoint() {
        // Below the highest point: a peak may rise anywhere in front, so the bottom row
        // looks straight down.
        let aux = aux_camera(&camera(-45.0), 16.0 / 9.0, 500.0, -50.0);
        assert!(aux.restricted);
        let (_, bottom) = rows(&aux);
        assert!(
            (bottom - std::f64::consts::FRAC_PI_2).abs() < 1e-9,
            "{bottom}"
        );
        // Above relief, the bottom row reaches the foot of the nearest point the main
        // camera's bottom row can see at the highest height.
        let main = camera(-45.0);
        let aux = aux_camera(&main, 16.0 / 9.0, 5000.0, 4000.0);
        assert!(aux.restricted);
        let (_, bottom) = rows(&aux);
        let main_bottom = -main.pitch + main.fov_y / 2.0;
        let foot = 4000.0 / main_bottom.tan();
        let want = (5000.0 / foot).atan();
        assert!((bottom - want).abs() < 1e-9, "{bottom} vs {want}");
        // Over flat ground, the main camera's own rows suffice.
        let aux = aux_camera(&main, 16.0 / 9.0, 5000.0, 5000.0);
        assert!(!aux.restricted);
    }

    #[test]
    fn the_restricted_camera_covers_the_main_cameras_width_at_the_horizon() {
        let main = camera(0.0);
        let aspect = 16.0 / 9.0;
        let aux = aux_camera(&main, aspect, 500.0, 100.0);
        // The main camera's right edge at the horizon, and the auxiliary top row's.
        let main_edge = ((main.fov_y / 2.0).tan() * aspect).atan();
        let top_right = aux.ray([1.0, 0.0]);
        let across = top_right.dot(aux.right).asin();
        assert!(across >= main_edge - 1e-9, "{across} < {main_edge}");
    }

    #[test]
    fn the_warp_crowds_rows_towards_the_horizon_and_keeps_the_ends() {
        let aux = aux_camera(&camera(-10.0), 16.0 / 9.0, 500.0, 100.0);
        let (u, v) = warp_tables(&aux, -500.0, 1e6);
        for table in [&u, &v] {
            assert_eq!(table[0], 0.0);
            assert_eq!(table[WARP_CELLS], 1.0);
            assert!(table.windows(2).all(|w| w[1] >= w[0]), "{table:?}");
        }
        // The top half of the screen (towards the horizon) gets more than half the rows.
        let half = v.iter().filter(|&&x| x < 0.5).count();
        assert!(
            half > WARP_CELLS / 2 + 2,
            "rows above the middle: {half} of {}",
            WARP_CELLS + 1
        );
        // Across, the grid stays about symmetric.
        assert!(
            (u[WARP_CELLS / 2] - 0.5).abs() < 0.05,
            "{}",
            u[WARP_CELLS / 2]
        );
    }

    #[test]
    fn a_uniform_density_leaves_the_grid_uniform() {
        let lines = inverse_cdf(&[1.0; WARP_CELLS]);
        for (k, x) in lines.iter().enumerate() {
            assert!((x - k as f64 / WARP_CELLS as f64).abs() < 1e-12, "{k}: {x}");
        }
    }
}
