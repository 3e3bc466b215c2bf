//! The per-sample rules every reader shares, whether it holds the whole file
//! ([`super::decode_heights`]) or streams it a row at a time ([`super::rows`]): which raw
//! values are no-data, and how float heights become integer codes.
//!
//! Integers are codes as they are. Floats need one decision about the whole raster first:
//! whole numbers keep a 1 m quantum (lossless), anything else is rounded to the caller's
//! quantum, and a sample no `i32` code holds at the chosen quantum is refused or made a void
//! ([`OutOfRange`]). [`FloatStats`] gathers what that decision needs, sample by sample in
//! any order of rows; [`FloatStats::finish`] makes it ([`FloatCodes`]), and
//! [`FloatCodes::code`] then converts each sample. A whole-file reader runs both over its
//! buffer; a streamed one runs the first during its scan and the second while building.

use super::{InputError, Metres, OutOfRange, SampleList};
use std::path::Path;

/// Samples named in an out-of-range message; the rest are counted.
const NAMED_SAMPLES: usize = 5;

/// No-data of integer samples.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum IntNodata {
    None,
    /// The value truncated to an integer and compared as one (PNG, `.hgt`).
    Code(i64),
    /// The value compared with each sample as a float (GeoTIFF integer samples, so that a
    /// tag of 3.5 matches nothing).
    Value(f64),
}

impl IntNodata {
    pub(crate) fn is_void(self, code: i32) -> bool {
        match self {
            IntNodata::None => false,
            IntNodata::Code(v) => i64::from(code) == v,
            IntNodata::Value(v) => f64::from(code) == v,
        }
    }
}

/// No-data of float samples: NaN always, and the file's value compared at the file's own
/// precision.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum FloatNodata {
    NanOnly,
    /// Float32 samples, compared in float32, so that a tag of "-3.4028235e+38" matches
    /// float32's lowest value, which as a float64 is -3.4028234663852886e+38.
    F32(f32),
    F64(f64),
}

impl FloatNodata {
    /// The rule for float32 samples (`nodata` as the file or the user gave it).
    pub(crate) fn for_f32(nodata: Option<f64>) -> FloatNodata {
        nodata.map_or(FloatNodata::NanOnly, |n| FloatNodata::F32(n as f32))
    }

    pub(crate) fn for_f64(nodata: Option<f64>) -> FloatNodata {
        nodata.map_or(FloatNodata::NanOnly, FloatNodata::F64)
    }

    pub(crate) fn is_void(self, x: f64) -> bool {
        x.is_nan()
            || match self {
                FloatNodata::NanOnly => false,
                FloatNodata::F32(n) => x as f32 == n,
                FloatNodata::F64(n) => x == n,
            }
    }
}

/// A float raster being turned into codes: where it came from and the caller's choices.
#[derive(Debug, Clone, Copy)]
pub(crate) struct FloatRaster<'a> {
    pub path: &'a Path,
    pub quantum_m: f64,
    pub out_of_range: OutOfRange,
}

/// What the choice of a quantum needs to know about every sample of a float raster.
#[derive(Debug, Clone)]
pub(crate) struct FloatStats {
    quantum_m: f64,
    samples: usize,
    no_data: usize,
    /// Every finite height is a whole number.
    whole: bool,
    /// Range of the finite heights any quantum worth using holds (see `finish`).
    plausible: (f64, f64),
    /// Samples no code holds at a 1 m quantum, and at `quantum_m`, and the range of those
    /// one does.
    outside_whole: SampleList,
    outside_quantum: SampleList,
    coded_whole: (f64, f64),
    coded_quantum: (f64, f64),
}

/// How a float raster's samples become codes, decided from all of them ([`FloatStats`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct FloatCodes {
    pub quantum_m: f64,
    /// Samples no code holds, made voids ([`OutOfRange::Nodata`]).
    pub out_of_range: usize,
    /// No-data samples, those out of range not counted.
    pub no_data: usize,
    /// Smallest and largest sample a code holds, `None` when there is none.
    pub coded: Option<(f64, f64)>,
}

impl FloatCodes {
    /// The code of sample `v` (not a no-data one), `None` when no code holds it.
    pub(crate) fn code(&self, v: f64) -> Option<i32> {
        code_at(v, self.quantum_m)
    }
}

fn code_at(v: f64, q: f64) -> Option<i32> {
    let code = (v / q).round();
    (f64::from(i32::MIN)..=f64::from(i32::MAX))
        .contains(&code)
        .then_some(code as i32)
}

fn note(list: &mut SampleList, x: u32, y: u32, v: f64) {
    if list.first.len() < NAMED_SAMPLES {
        list.first.push((x, y, v));
    } else {
        list.more += 1;
    }
}

impl FloatStats {
    pub(crate) fn new(quantum_m: f64) -> FloatStats {
        let empty = SampleList {
            first: Vec::new(),
            more: 0,
        };
        FloatStats {
            quantum_m,
            samples: 0,
            no_data: 0,
            whole: true,
            plausible: (f64::INFINITY, f64::NEG_INFINITY),
            outside_whole: empty.clone(),
            outside_quantum: empty,
            coded_whole: (f64::INFINITY, f64::NEG_INFINITY),
            coded_quantum: (f64::INFINITY, f64::NEG_INFINITY),
        }
    }

    /// Adds sample `v` at `(x, y)`; samples must come in row-major order, so that the
    /// first few out of range are the ones a message names.
    pub(crate) fn add(&mut self, x: u32, y: u32, v: f64, no_data: bool) {
        self.samples += 1;
        if no_data {
            self.no_data += 1;
            return;
        }
        if v.is_finite() {
            self.whole &= v.fract() == 0.0;
            if v.abs() <= plausible_m() {
                self.plausible = (self.plausible.0.min(v), self.plausible.1.max(v));
            }
        }
        for (q, outside, coded) in [
            (1.0, &mut self.outside_whole, &mut self.coded_whole),
            (
                self.quantum_m,
                &mut self.outside_quantum,
                &mut self.coded_quantum,
            ),
        ] {
            if code_at(v, q).is_none() {
                note(outside, x, y, v);
            } else {
                *coded = (coded.0.min(v), coded.1.max(v));
            }
        }
    }

    /// Chooses the quantum: 1 m when every height is whole, else the caller's. A sample no
    /// code holds at it is refused or made a void, as [`OutOfRange`] says; a quantum too fine
    /// for the samples' own range is refused either way, since making voids of real heights
    /// would hide the mistake.
    pub(crate) fn finish(self, raster: &FloatRaster<'_>) -> Result<FloatCodes, InputError> {
        let (q, outside, coded) = if self.whole {
            (1.0, self.outside_whole, self.coded_whole)
        } else {
            (self.quantum_m, self.outside_quantum, self.coded_quantum)
        };
        let limit_m = Metres(q * f64::from(i32::MAX));
        let (min_m, max_m) = self.plausible;
        if min_m <= max_m && (code_at(min_m, q).is_none() || code_at(max_m, q).is_none()) {
            return Err(InputError::QuantumTooFine {
                path: raster.path.into(),
                quantum_m: Metres(q),
                limit_m,
                min_m,
                max_m,
                needed_m: round_up_2_digits(min_m.abs().max(max_m.abs()) / f64::from(i32::MAX)),
            });
        }
        let count = outside.first.len() + outside.more;
        if count > 0 && raster.out_of_range == OutOfRange::Refuse {
            return Err(InputError::OutOfRange {
                path: raster.path.into(),
                count,
                total: self.samples,
                quantum_m: Metres(q),
                limit_m,
                samples: outside,
            });
        }
        Ok(FloatCodes {
            quantum_m: q,
            out_of_range: count,
            no_data: self.no_data,
            coded: (coded.0 <= coded.1).then_some(coded),
        })
    }
}

/// The samples' own range: every finite height the default quantum can hold, which is any
/// height on Earth in metres or even millimetres (±21,474 km); values past it are no-data
/// markers such as -3.4e38 and 1e30, not heights.
fn plausible_m() -> f64 {
    crate::build::DEFAULT_FLOAT_QUANTUM_M * f64::from(i32::MAX)
}

/// `x` rounded up to two significant digits, so that a suggested quantum is never too fine.
fn round_up_2_digits(x: f64) -> f64 {
    let step = 10f64.powf(x.log10().floor() - 1.0);
    (x / step).ceil() * step
}
