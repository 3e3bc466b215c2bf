//! Camera paths for flights: keyframes in time, interpolated linearly. Pure: the flight
//! asks for the position at a time, nothing here reads a clock.
//!
//! Two file formats, documented in `docs/flight.md`:
//!
//! - JSON: `{"units": "metres" | "extent", "keyframes": [{"t": 0, "x": .., "y": .., "z": ..}, ...]}`;
//!   with `"extent"`, x and y are fractions of the terrain's extent (0 = west/north edge,
//!   1 = east/south edge) so one path fits any dataset; z is always metres.
//! - CSV: a header `t,x,y,z` then one keyframe per line, metres.
//!
//! Coordinates: x east and y south from raster sample (0, 0) (the north-west corner), z up,
//! t in seconds from the start.

use serde::Deserialize;
use std::path::Path;
use terrain_shared::Manifest;
use thiserror::Error;

/// Tiles per second the default path moves at: slow enough that paging keeps up on a
/// local link, fast enough to cross the largest kit terrain (32 tiles) in under a minute.
pub const DEFAULT_SPEED_TILES_PER_S: f64 = 2.0;
/// The default path never lasts less than this, so small terrains still page belt by belt.
pub const DEFAULT_MIN_MOVING_S: f64 = 8.0;
/// Seconds the default path holds still at its end, so the square can converge.
pub const DEFAULT_HOLD_S: f64 = 4.0;

/// One point of a path.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
pub struct Keyframe {
    pub t: f64,
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

/// Why a path file was refused.
#[derive(Debug, Error)]
pub enum PathError {
    #[error("cannot read flight path {path}")]
    Io {
        path: String,
        source: std::io::Error,
    },
    #[error("flight path {path} is not valid JSON for a path: {message}")]
    Json { path: String, message: String },
    #[error("flight path {path}, line {line}: {message}")]
    Csv {
        path: String,
        line: usize,
        message: String,
    },
    #[error("flight path {path}: {message}")]
    Invalid { path: String, message: String },
}

#[derive(Debug, Deserialize)]
#[serde(rename_all = "lowercase")]
enum Units {
    Metres,
    Extent,
}

#[derive(Debug, Deserialize)]
struct PathFile {
    #[serde(default = "default_units")]
    units: Units,
    keyframes: Vec<Keyframe>,
}

fn default_units() -> Units {
    Units::Metres
}

/// A validated path: at least one keyframe, times finite and non-decreasing.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraPath {
    keyframes: Vec<Keyframe>,
}

impl CameraPath {
    /// Keyframes in metres.
    pub fn new(keyframes: Vec<Keyframe>) -> Result<CameraPath, String> {
        if keyframes.is_empty() {
            return Err("a path needs at least one keyframe".into());
        }
        for (i, k) in keyframes.iter().enumerate() {
            if ![k.t, k.x, k.y, k.z].iter().all(|v| v.is_finite()) {
                return Err(format!(
                    "keyframe {i} has a value that is not a finite number"
                ));
            }
            if i > 0 && k.t < keyframes[i - 1].t {
                return Err(format!(
                    "keyframe {i} at t = {} s comes before the previous one",
                    k.t
                ));
            }
        }
        Ok(CameraPath { keyframes })
    }

    /// Reads a `.json` or `.csv` path; `extent` units are resolved against `manifest`.
    pub fn load(path: &Path, manifest: &Manifest) -> Result<CameraPath, PathError> {
        let name = path.display().to_string();
        let text = read_path_file(path).map_err(|source| PathError::Io {
            path: name.clone(),
            source,
        })?;
        let is_csv = path
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("csv"));
        let keyframes = if is_csv {
            parse_csv(&text, &name)?
        } else {
            parse_json(&text, &name, manifest)?
        };
        CameraPath::new(keyframes).map_err(|message| PathError::Invalid {
            path: name,
            message,
        })
    }

    /// A lap over the whole terrain: the four quadrants in turn, then the centre, at
    /// [`DEFAULT_SPEED_TILES_PER_S`], a bird's eye above the highest point, then a
    /// [`DEFAULT_HOLD_S`] hold.
    pub fn default_for(manifest: &Manifest) -> CameraPath {
        let [w, h] = manifest.extent_m;
        let tile_m =
            f64::from(manifest.tile_size - 1) * manifest.spacing_m[0].max(manifest.spacing_m[1]);
        let z = manifest.heights.max_m + 0.05 * w.max(h);
        let stops = [
            (0.15, 0.15),
            (0.85, 0.15),
            (0.85, 0.85),
            (0.15, 0.85),
            (0.5, 0.5),
        ];
        let length_m: f64 = stops
            .windows(2)
            .map(|p| ((p[1].0 - p[0].0) * w).hypot((p[1].1 - p[0].1) * h))
            .sum();
        let moving_s = (length_m / tile_m / DEFAULT_SPEED_TILES_PER_S).max(DEFAULT_MIN_MOVING_S);
        let mut t = 0.0;
        let mut keyframes = vec![Keyframe {
            t,
            x: stops[0].0 * w,
            y: stops[0].1 * h,
            z,
        }];
        for p in stops.windows(2) {
            t += moving_s * ((p[1].0 - p[0].0) * w).hypot((p[1].1 - p[0].1) * h) / length_m;
            keyframes.push(Keyframe {
                t,
                x: p[1].0 * w,
                y: p[1].1 * h,
                z,
            });
        }
        let last = keyframes[keyframes.len() - 1];
        keyframes.push(Keyframe {
            t: t + DEFAULT_HOLD_S,
            ..last
        });
        CameraPath { keyframes }
    }

    pub fn keyframes(&self) -> &[Keyframe] {
        &self.keyframes
    }

    /// Time of the last keyframe.
    pub fn duration_s(&self) -> f64 {
        self.keyframes[self.keyframes.len() - 1].t
    }

    /// Position `[x, y, z]` in metres at time `t`, held at the ends.
    pub fn position_at(&self, t: f64) -> [f64; 3] {
        let k = &self.keyframes;
        let next = k.partition_point(|f| f.t <= t);
        if next == 0 {
            return [k[0].x, k[0].y, k[0].z];
        }
        if next == k.len() {
            let l = k[k.len() - 1];
            return [l.x, l.y, l.z];
        }
        let (a, b) = (k[next - 1], k[next]);
        let f = if b.t > a.t {
            (t - a.t) / (b.t - a.t)
        } else {
            1.0
        };
        [
            a.x + (b.x - a.x) * f,
            a.y + (b.y - a.y) * f,
            a.z + (b.z - a.z) * f,
        ]
    }
}

/// The camera's heading along the path: towards where the path is in a second, or the last
/// heading when the path holds still.
pub fn heading(path: &CameraPath, time_s: f64, previous: f64) -> f64 {
    let a = path.position_at(time_s);
    let b = path.position_at(time_s + 1.0);
    let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
    if dx.hypot(dy) < 1e-3 {
        previous
    } else {
        dy.atan2(dx)
    }
}

fn parse_json(text: &str, name: &str, manifest: &Manifest) -> Result<Vec<Keyframe>, PathError> {
    let file: PathFile = serde_json::from_str(text).map_err(|e| PathError::Json {
        path: name.into(),
        message: e.to_string(),
    })?;
    Ok(match file.units {
        Units::Metres => file.keyframes,
        Units::Extent => file
            .keyframes
            .into_iter()
            .map(|k| Keyframe {
                x: k.x * manifest.extent_m[0],
                y: k.y * manifest.extent_m[1],
                ..k
            })
            .collect(),
    })
}

fn parse_csv(text: &str, name: &str) -> Result<Vec<Keyframe>, PathError> {
    let mut lines = text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty() && !l.trim_start().starts_with('#'));
    let header: Vec<String> = lines
        .next()
        .map(|(_, l)| {
            l.split(',')
                .map(|c| c.trim().to_ascii_lowercase())
                .collect()
        })
        .unwrap_or_default();
    if header != ["t", "x", "y", "z"] {
        return Err(PathError::Csv {
            path: name.into(),
            line: 1,
            message: "the header must be t,x,y,z".into(),
        });
    }
    lines
        .map(|(i, line)| {
            let values: Result<Vec<f64>, _> =
                line.split(',').map(|v| v.trim().parse::<f64>()).collect();
            match values.as_deref() {
                Ok([t, x, y, z]) => Ok(Keyframe {
                    t: *t,
                    x: *x,
                    y: *y,
                    z: *z,
                }),
                _ => Err(PathError::Csv {
                    path: name.into(),
                    line: i + 1,
                    message: format!("expected four numbers, got {line:?}"),
                }),
            }
        })
        .collect()
}

/// The most bytes a camera path file may have: millions of keyframes.
pub const MAX_PATH_FILE_BYTES: u64 = 64 << 20;

/// Reads a camera path file: a regular file of at most [`MAX_PATH_FILE_BYTES`], read no
/// further than that whatever it is (`/dev/zero`, a FIFO, a file growing as it is read).
fn read_path_file(path: &Path) -> std::io::Result<String> {
    use std::io::Read;
    let file = std::fs::File::open(path)?;
    let meta = file.metadata()?;
    if !meta.is_file() {
        return Err(std::io::Error::other(
            "not a regular file (a device, a FIFO or a directory): a camera path is a .json or .csv file",
        ));
    }
    if meta.len() > MAX_PATH_FILE_BYTES {
        return Err(std::io::Error::other(format!(
            "{} bytes, more than the {MAX_PATH_FILE_BYTES} a camera path may have",
            meta.len()
        )));
    }
    let mut text = String::new();
    file.take(MAX_PATH_FILE_BYTES + 1)
        .read_to_string(&mut text)?;
    if text.len() as u64 > MAX_PATH_FILE_BYTES {
        return Err(std::io::Error::other(format!(
            "it grew past the {MAX_PATH_FILE_BYTES} bytes a camera path may have as it was read"
        )));
    }
    Ok(text)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn path(points: &[(f64, f64, f64, f64)]) -> CameraPath {
        CameraPath::new(
            points
                .iter()
                .map(|&(t, x, y, z)| Keyframe { t, x, y, z })
                .collect(),
        )
        .expect("valid")
    }

    #[test]
    fn positions_interpolate_between_keyframes_and_hold_at_the_ends() {
        let p = path(&[
            (0.0, 0.0, 0.0, 10.0),
            (2.0, 100.0, 50.0, 10.0),
            (2.0, 0.0, 0.0, 0.0),
            (3.0, 0.0, 10.0, 0.0),
        ]);
        assert_eq!(p.position_at(-1.0), [0.0, 0.0, 10.0]);
        assert_eq!(p.position_at(1.0), [50.0, 25.0, 10.0]);
        assert_eq!(
            p.position_at(2.0),
            [0.0, 0.0, 0.0],
            "two keyframes at one time: a jump"
        );
        assert_eq!(p.position_at(2.5), [0.0, 5.0, 0.0]);
        assert_eq!(p.position_at(9.0), [0.0, 10.0, 0.0]);
        assert_eq!(p.duration_s(), 3.0);
    }

    #[test]
    fn invalid_paths_say_what_is_wrong() {
        assert!(CameraPath::new(vec![]).is_err());
        let back = vec![
            Keyframe {
                t: 1.0,
                x: 0.0,
                y: 0.0,
                z: 0.0,
            },
            Keyframe {
                t: 0.5,
                x: 0.0,
                y: 0.0,
                z: 0.0,
            },
        ];
        assert!(
            CameraPath::new(back)
                .expect_err("time runs back")
                .contains("before")
        );
        assert!(matches!(
            parse_csv("t,x,y\n0,1,2\n", "p.csv"),
            Err(PathError::Csv { line: 1, .. })
        ));
        assert!(matches!(
            parse_csv("t,x,y,z\n0,1,2\n", "p.csv"),
            Err(PathError::Csv { line: 2, .. })
        ));
    }

    #[test]
    fn csv_paths_read_metres() {
        let k =
            parse_csv("# a comment\nt, x, y, z\n0,1,2,3\n\n1.5,4,5,6\n", "p.csv").expect("valid");
        assert_eq!(
            k,
            vec![
                Keyframe {
                    t: 0.0,
                    x: 1.0,
                    y: 2.0,
                    z: 3.0
                },
                Keyframe {
                    t: 1.5,
                    x: 4.0,
                    y: 5.0,
                    z: 6.0
                }
            ]
        );
    }
}
