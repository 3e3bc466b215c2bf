//! The heights codec: one tile's height samples, lossless at the source's height quantum.
//!
//! A tile is a `width x height` grid of integer height *codes*; metres are
//! `offset_m + quantum_m * code`. Encoding runs two steps:
//!
//! 1. **Prediction.** Each code is predicted from its west, north and north-west
//!    neighbours as `west + north - north_west` (the planar predictor, exact on any
//!    tilted plane, which most terrain locally is) and only the residual is kept, zig-zag
//!    mapped to an unsigned integer. Codes are first made relative to the tile minimum so
//!    the first sample is small.
//! 2. **Entropy coding**, by one of two coders (the header's codec version says which):
//!    - **version 2, rANS with contexts** (written by default, [`Coder::Rans`]): each
//!      residual is coded under a context of the residuals of the row above, with
//!      frequency tables made for the tile (`rans.rs` has the details). It comes within a
//!      few percent of the residuals' entropy given their local gradient, which no
//!      general-purpose coder reaches, and codes and decodes a row at a time.
//!    - **version 1, byte planes and zstd** ([`Coder::Zstd`]): the residuals split into
//!      planes (all low bytes, then all second bytes, as many as the largest residual
//!      needs), one zstd frame per plane. Still read, and written on request.
//!
//! Decoding undoes them in one pass per row: the residual of the planar predictor is
//! a mixed second difference, so the codes are a running sum along the row added to
//! the row above. Only the running sum is serial; everything else vectorises.
//!
//! The header is versioned and checksummed; [`Heights::decode`] returns an error, never
//! panics, for any byte string (see the property tests at the bottom of this file).
//!
//! Layout (little endian), 44 bytes then the payload:
//!
//! | bytes | field |
//! |---|---|
//! | 4 | magic `THGT` |
//! | 1 | codec version (2, or 1) |
//! | 1 | version 1: residual byte planes (1..=4); version 2: zero |
//! | 2 | reserved, zero |
//! | 2 + 2 | width, height in samples |
//! | 8 + 8 | quantum and offset in metres (f64) |
//! | 4 + 4 | minimum and maximum code (i32) |
//! | 4 | payload length in bytes |
//! | 4 | CRC-32 of every byte before it and of the payload |
//!
//! Version 2's payload: the byte lengths of the tables and of the raw bits (u32 each), the
//! tables, the raw bits, then the rANS words (u16). Version 1's: one zstd frame per plane,
//! low byte plane first.

use thiserror::Error;

/// The four bytes every encoded heights tile starts with.
pub const MAGIC: [u8; 4] = *b"THGT";
/// The codec version this crate writes by default ([`Coder::Rans`]); it also reads
/// [`ZSTD_CODEC_VERSION`].
pub const CODEC_VERSION: u8 = 2;
/// The version of the byte-plane zstd coder ([`Coder::Zstd`]).
pub const ZSTD_CODEC_VERSION: u8 = 1;
/// The name of the default codec in the manifest.
pub const CODEC_NAME: &str = "planar-rans/2";
/// The name of the byte-plane zstd codec in the manifest.
pub const ZSTD_CODEC_NAME: &str = "planar-zstd/1";
/// Largest tile side the decoder accepts. Bounds the allocation a hostile header can ask
/// for: 8193^2 codes are 268 MB, far above any tile (the builder's largest is 4097).
pub const MAX_SIDE: u16 = 8193;
/// zstd level used by default (for [`Coder::Zstd`], and by the quadtree patches): the builder
/// runs once and clients decode many times; zstd decompression speed barely depends on the
/// level, so the strongest is free at read time.
pub const DEFAULT_ZSTD_LEVEL: i32 = 19;

/// Which entropy coder [`Heights::encode_with`] uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Coder {
    /// Codec version 2: context-modelled rANS (the default).
    Rans,
    /// Codec version 1: byte planes, one zstd frame each, at this level (1..=22).
    Zstd(i32),
}

impl Coder {
    /// The codec's name in the manifest.
    pub fn name(self) -> &'static str {
        match self {
            Coder::Rans => CODEC_NAME,
            Coder::Zstd(_) => ZSTD_CODEC_NAME,
        }
    }
}

const HEADER_LEN: usize = 44;

#[cfg(not(target_arch = "wasm32"))]
thread_local! {
    /// One zstd decompression context per thread: creating one per call costs more than
    /// decompressing a small plane (measured: decode throughput +15% on puget_sound_1k).
    static DECOMPRESSOR: std::cell::RefCell<Option<zstd::bulk::Decompressor<'static>>> =
        std::cell::RefCell::new(zstd::bulk::Decompressor::new().ok());
}
const CRC_OFFSET: usize = HEADER_LEN - 4;

/// One tile of height codes, row-major, row 0 at the north edge.
#[derive(Debug, Clone, PartialEq)]
pub struct Heights {
    pub width: u16,
    pub height: u16,
    /// Metres per code step.
    pub quantum_m: f64,
    /// Metres at code 0.
    pub offset_m: f64,
    pub codes: Vec<i32>,
}

/// Why a tile could not be encoded.
#[derive(Debug, Error, PartialEq)]
pub enum EncodeError {
    #[error("tile of {width}x{height} samples: each side must be between 1 and {MAX_SIDE}")]
    BadSize { width: usize, height: usize },
    #[error("{codes} codes given for a {width}x{height} tile")]
    WrongLength {
        codes: usize,
        width: u16,
        height: u16,
    },
    #[error("height quantum {0} m is not a positive finite number")]
    BadQuantum(f64),
    #[error("zstd failed: {0}")]
    Zstd(String),
}

/// Why bytes could not be decoded into a tile. Every corrupt or truncated input maps here.
#[derive(Debug, Error, PartialEq)]
pub enum DecodeError {
    #[error("truncated heights tile: {len} bytes, the header alone needs {HEADER_LEN}")]
    TruncatedHeader { len: usize },
    #[error("not a heights tile: magic {found:?}, expected {MAGIC:?}")]
    BadMagic { found: [u8; 4] },
    #[error(
        "heights codec version {0} is not supported (this build reads {ZSTD_CODEC_VERSION} and {CODEC_VERSION})"
    )]
    UnsupportedVersion(u8),
    #[error("corrupt heights header: {0}")]
    BadHeader(&'static str),
    #[error("heights payload is {found} bytes, the header says {expected}")]
    PayloadLength { expected: usize, found: usize },
    #[error("heights checksum mismatch: stored {stored:#010x}, computed {computed:#010x}")]
    Checksum { stored: u32, computed: u32 },
    #[error("heights payload does not decompress: {0}")]
    Zstd(String),
    #[error("heights payload does not decode: {0}")]
    Rans(String),
    #[error(
        "heights plane {plane} says it decompresses to {claimed} bytes, more than the {allowed} bytes of a {width}x{height} tile"
    )]
    PlaneTooLarge {
        plane: usize,
        allowed: usize,
        claimed: u64,
        width: u16,
        height: u16,
    },
    #[error(
        "heights plane {plane} decompresses past the {allowed} bytes of a {width}x{height} tile (its frame does not state its size)"
    )]
    PlanePastTile {
        plane: usize,
        allowed: usize,
        width: u16,
        height: u16,
    },
    #[error("decoded codes span {found:?}, the header says {expected:?}")]
    RangeMismatch {
        expected: (i32, i32),
        found: (i32, i32),
    },
}

impl Heights {
    /// Metres of sample `(x, y)`.
    pub fn metres(&self, x: usize, y: usize) -> f64 {
        self.offset_m + self.quantum_m * f64::from(self.codes[y * usize::from(self.width) + x])
    }

    /// All samples in metres as `f32`, row-major: what a renderer uploads.
    pub fn to_metres_f32(&self) -> Vec<f32> {
        self.codes
            .iter()
            .map(|&c| (self.offset_m + self.quantum_m * f64::from(c)) as f32)
            .collect()
    }

    /// Smallest and largest code; `(0, 0)` for an empty tile.
    pub fn code_range(&self) -> (i32, i32) {
        let min = self.codes.iter().copied().min().unwrap_or(0);
        let max = self.codes.iter().copied().max().unwrap_or(0);
        (min, max)
    }

    /// Encodes with the default coder ([`Coder::Rans`]).
    pub fn encode(&self) -> Result<Vec<u8>, EncodeError> {
        self.encode_with(Coder::Rans)
    }

    /// Encodes with the byte-plane zstd coder (codec version 1) at `zstd_level` (1..=22).
    pub fn encode_with_level(&self, zstd_level: i32) -> Result<Vec<u8>, EncodeError> {
        self.encode_with(Coder::Zstd(zstd_level))
    }

    /// Encodes with the given coder.
    pub fn encode_with(&self, coder: Coder) -> Result<Vec<u8>, EncodeError> {
        let (w, h) = (usize::from(self.width), usize::from(self.height));
        if w == 0 || h == 0 || self.width > MAX_SIDE || self.height > MAX_SIDE {
            return Err(EncodeError::BadSize {
                width: w,
                height: h,
            });
        }
        if self.codes.len() != w * h {
            return Err(EncodeError::WrongLength {
                codes: self.codes.len(),
                width: self.width,
                height: self.height,
            });
        }
        if !(self.quantum_m.is_finite() && self.quantum_m > 0.0) {
            return Err(EncodeError::BadQuantum(self.quantum_m));
        }
        let (min, max) = self.code_range();

        // Residuals of the planar predictor over codes relative to the minimum. Wrapping
        // arithmetic: the decoder wraps the same way, so any i32 range round-trips.
        let rel = |x: usize, y: usize| self.codes[y * w + x].wrapping_sub(min);
        let mut zigzag = Vec::with_capacity(w * h);
        for y in 0..h {
            for x in 0..w {
                let west = if x > 0 { rel(x - 1, y) } else { 0 };
                let north = if y > 0 { rel(x, y - 1) } else { 0 };
                let north_west = if x > 0 && y > 0 { rel(x - 1, y - 1) } else { 0 };
                let prediction = west.wrapping_add(north).wrapping_sub(north_west);
                zigzag.push(zigzag_encode(rel(x, y).wrapping_sub(prediction)));
            }
        }
        let (version, planes_byte, payload) = match coder {
            Coder::Rans => (CODEC_VERSION, 0u8, crate::rans::encode(&zigzag, w)),
            Coder::Zstd(zstd_level) => {
                let planes = planes_needed(zigzag.iter().copied().max().unwrap_or(0));
                let mut plane = vec![0u8; w * h];
                let mut payload = Vec::new();
                for index in 0..planes {
                    for (dst, z) in plane.iter_mut().zip(&zigzag) {
                        *dst = (z >> (8 * index)) as u8;
                    }
                    let frame = zstd_compress(&plane, zstd_level)?;
                    payload.extend_from_slice(&frame);
                }
                (ZSTD_CODEC_VERSION, planes as u8, payload)
            }
        };
        let mut out = Vec::with_capacity(HEADER_LEN + payload.len());
        out.extend_from_slice(&MAGIC);
        out.push(version);
        out.push(planes_byte);
        out.extend_from_slice(&0u16.to_le_bytes());
        out.extend_from_slice(&self.width.to_le_bytes());
        out.extend_from_slice(&self.height.to_le_bytes());
        out.extend_from_slice(&self.quantum_m.to_le_bytes());
        out.extend_from_slice(&self.offset_m.to_le_bytes());
        out.extend_from_slice(&min.to_le_bytes());
        out.extend_from_slice(&max.to_le_bytes());
        let payload_len = u32::try_from(payload.len())
            .map_err(|_| EncodeError::Zstd("payload over 4 GiB".into()))?;
        out.extend_from_slice(&payload_len.to_le_bytes());
        let mut crc = crc32fast::Hasher::new();
        crc.update(&out);
        crc.update(&payload);
        out.extend_from_slice(&crc.finalize().to_le_bytes());
        out.extend_from_slice(&payload);
        Ok(out)
    }

    /// Decodes one tile, verifying the header, the checksum and the decoded range.
    pub fn decode(bytes: &[u8]) -> Result<Heights, DecodeError> {
        let header = Header::parse(bytes)?;
        let (w, h) = (usize::from(header.width), usize::from(header.height));
        let payload = &bytes[HEADER_LEN..];
        let mut codes = vec![0i32; w * h];
        if header.version == CODEC_VERSION {
            crate::rans::decode(payload, w, h, |y, zigzag| {
                reconstruct_row(&mut codes, w, y, zigzag)
            })
            .map_err(|e| DecodeError::Rans(e.to_string()))?;
        } else {
            decode_planes(&header, payload, &mut codes)?;
        }
        let mut lo = i32::MAX;
        let mut hi = i32::MIN;
        for c in &mut codes {
            *c = c.wrapping_add(header.min);
            lo = lo.min(*c);
            hi = hi.max(*c);
        }
        if (lo, hi) != (header.min, header.max) {
            return Err(DecodeError::RangeMismatch {
                expected: (header.min, header.max),
                found: (lo, hi),
            });
        }
        Ok(Heights {
            width: header.width,
            height: header.height,
            quantum_m: header.quantum_m,
            offset_m: header.offset_m,
            codes,
        })
    }
}

/// Puts row `y`'s codes (relative to the minimum) in place from its zig-zag residuals:
/// `code(x, y) - code(x, y-1)` is the running sum of residuals along the row.
fn reconstruct_row(codes: &mut [i32], w: usize, y: usize, zigzag: &[u32]) {
    let (above, row) = codes.split_at_mut(y * w);
    let row = &mut row[..w];
    let mut running = 0i32;
    if y == 0 {
        for (dst, &z) in row.iter_mut().zip(zigzag) {
            running = running.wrapping_add(zigzag_decode(z));
            *dst = running;
        }
    } else {
        let above = &above[(y - 1) * w..];
        for ((dst, &z), &up) in row.iter_mut().zip(zigzag).zip(above) {
            running = running.wrapping_add(zigzag_decode(z));
            *dst = up.wrapping_add(running);
        }
    }
}

/// One zstd frame of `plane` at `level`.
#[cfg(not(target_arch = "wasm32"))]
fn zstd_compress(plane: &[u8], level: i32) -> Result<Vec<u8>, EncodeError> {
    zstd::bulk::compress(plane, level).map_err(|e| EncodeError::Zstd(e.to_string()))
}

/// The browser build has no zstd C library (it does not build for the page without a C
/// toolchain for it): it reads codec version 1 (with ruzstd) but does not write it.
#[cfg(target_arch = "wasm32")]
fn zstd_compress(_plane: &[u8], _level: i32) -> Result<Vec<u8>, EncodeError> {
    Err(EncodeError::Zstd(
        "the browser build does not write planar-zstd/1 heights".into(),
    ))
}

/// Codec version 1 in the browser build: the planes' frames read with ruzstd
/// ([`crate::zstd_frames`]), checked as natively.
#[cfg(target_arch = "wasm32")]
fn decode_planes(header: &Header, payload: &[u8], codes: &mut [i32]) -> Result<(), DecodeError> {
    decode_planes_in_rust(header, payload, codes)
}

/// [`decode_planes`] with ruzstd instead of zstd's C library: the browser build's, and
/// the tests', which check it against the native one.
#[cfg(any(target_arch = "wasm32", test))]
fn decode_planes_in_rust(
    header: &Header,
    payload: &[u8],
    codes: &mut [i32],
) -> Result<(), DecodeError> {
    use crate::zstd_frames::{FrameError, decode_frame_into};
    let n = usize::from(header.width) * usize::from(header.height);
    let mut planar = vec![0u8; n * header.planes];
    let mut rest = payload;
    for (index, plane) in planar.chunks_exact_mut(n).enumerate() {
        let (written, taken) = decode_frame_into(rest, plane).map_err(|e| match e {
            FrameError::PastEnd => DecodeError::PlanePastTile {
                plane: index,
                allowed: n,
                width: header.width,
                height: header.height,
            },
            FrameError::Zstd(why) => DecodeError::Zstd(why),
        })?;
        whole_plane(written, n)?;
        rest = &rest[taken..];
    }
    reassemble_planes(header, &planar, rest, codes)
}

/// Codec version 1: decompresses the byte planes and reconstructs the codes from them.
#[cfg(not(target_arch = "wasm32"))]
fn decode_planes(header: &Header, payload: &[u8], codes: &mut [i32]) -> Result<(), DecodeError> {
    let (w, h) = (usize::from(header.width), usize::from(header.height));
    let n = w * h;
    // One zstd frame per plane, back to back; frames are self-delimiting.
    let mut planar = vec![0u8; n * header.planes];
    let mut rest = payload;
    for (index, plane) in planar.chunks_exact_mut(n).enumerate() {
        let frame_len = zstd::zstd_safe::find_frame_compressed_size(rest)
            .map_err(|code| DecodeError::Zstd(zstd::zstd_safe::get_error_name(code).to_string()))?;
        let Some((frame, tail)) = rest.split_at_checked(frame_len) else {
            return Err(DecodeError::Zstd("frame runs past the payload".into()));
        };
        // A plane can never be larger than the tile: a frame that says so is refused
        // unread, and one that does not say is stopped where the plane's buffer ends.
        let claimed = zstd::zstd_safe::get_frame_content_size(frame)
            .map_err(|_| DecodeError::Zstd("unreadable frame header".into()))?;
        if let Some(claimed) = claimed.filter(|&c| c > n as u64) {
            return Err(DecodeError::PlaneTooLarge {
                plane: index,
                allowed: n,
                claimed,
                width: header.width,
                height: header.height,
            });
        }
        let written = match claimed {
            Some(_) => DECOMPRESSOR
                .with_borrow_mut(|d| d.as_mut().map(|d| d.decompress_to_buffer(frame, plane)))
                .ok_or_else(|| DecodeError::Zstd("no zstd context".into()))?
                .map_err(|e| DecodeError::Zstd(e.to_string()))?,
            // Frames of this codec's encoder always state their size; any other is
            // streamed, a byte past the plane being enough to refuse it.
            None => decompress_unsized(frame, plane).map_err(|e| match e {
                Unsized::PastTile => DecodeError::PlanePastTile {
                    plane: index,
                    allowed: n,
                    width: header.width,
                    height: header.height,
                },
                Unsized::Zstd(e) => DecodeError::Zstd(e.to_string()),
            })?,
        };
        whole_plane(written, n)?;
        rest = tail;
    }
    reassemble_planes(header, &planar, rest, codes)
}

/// A plane decompressed to `written` bytes of the tile's `n`: an error unless whole.
fn whole_plane(written: usize, n: usize) -> Result<(), DecodeError> {
    if written != n {
        return Err(DecodeError::Zstd(format!(
            "plane of {written} bytes, {n} expected"
        )));
    }
    Ok(())
}

/// The codes from codec version 1's decompressed byte planes (`planar`, plane after plane),
/// the payload's `rest` after the last plane being empty.
fn reassemble_planes(
    header: &Header,
    planar: &[u8],
    rest: &[u8],
    codes: &mut [i32],
) -> Result<(), DecodeError> {
    if !rest.is_empty() {
        return Err(DecodeError::Zstd(format!(
            "{} bytes after the last plane",
            rest.len()
        )));
    }
    let (w, h) = (usize::from(header.width), usize::from(header.height));
    let n = w * h;
    let mut zigzag = vec![0u32; w];
    for y in 0..h {
        // Reassemble this row's zig-zag residuals from the planes.
        for (x, z) in zigzag.iter_mut().enumerate() {
            *z = u32::from(planar[y * w + x]);
        }
        for plane in 1..header.planes {
            let src = &planar[plane * n + y * w..plane * n + (y + 1) * w];
            for (z, &b) in zigzag.iter_mut().zip(src) {
                *z |= u32::from(b) << (8 * plane);
            }
        }
        reconstruct_row(codes, w, y, &zigzag);
    }
    Ok(())
}

/// The parsed, validated fixed-size header.
#[derive(Debug, Clone, Copy)]
struct Header {
    version: u8,
    planes: usize,
    width: u16,
    height: u16,
    quantum_m: f64,
    offset_m: f64,
    min: i32,
    max: i32,
}

impl Header {
    fn parse(bytes: &[u8]) -> Result<Header, DecodeError> {
        let Some(head) = bytes.get(..HEADER_LEN) else {
            return Err(DecodeError::TruncatedHeader { len: bytes.len() });
        };
        let u16_at = |i: usize| u16::from_le_bytes([head[i], head[i + 1]]);
        let u32_at =
            |i: usize| u32::from_le_bytes([head[i], head[i + 1], head[i + 2], head[i + 3]]);
        let f64_at = |i: usize| {
            let mut b = [0u8; 8];
            b.copy_from_slice(&head[i..i + 8]);
            f64::from_le_bytes(b)
        };
        let magic = [head[0], head[1], head[2], head[3]];
        if magic != MAGIC {
            return Err(DecodeError::BadMagic { found: magic });
        }
        let version = head[4];
        if version != CODEC_VERSION && version != ZSTD_CODEC_VERSION {
            return Err(DecodeError::UnsupportedVersion(version));
        }
        let payload_len = u32_at(36) as usize;
        let found = bytes.len() - HEADER_LEN;
        if payload_len != found {
            return Err(DecodeError::PayloadLength {
                expected: payload_len,
                found,
            });
        }
        let stored = u32_at(CRC_OFFSET);
        let mut crc = crc32fast::Hasher::new();
        crc.update(&head[..CRC_OFFSET]);
        crc.update(&bytes[HEADER_LEN..]);
        let computed = crc.finalize();
        if stored != computed {
            return Err(DecodeError::Checksum { stored, computed });
        }
        let header = Header {
            version,
            planes: usize::from(head[5]),
            width: u16_at(8),
            height: u16_at(10),
            quantum_m: f64_at(12),
            offset_m: f64_at(20),
            min: u32_at(28) as i32,
            max: u32_at(32) as i32,
        };
        if version == ZSTD_CODEC_VERSION && !(1..=4).contains(&header.planes) {
            return Err(DecodeError::BadHeader("byte planes must be 1 to 4"));
        }
        if version == CODEC_VERSION && header.planes != 0 {
            return Err(DecodeError::BadHeader("byte planes must be 0 in version 2"));
        }
        if header.width == 0 || header.height == 0 {
            return Err(DecodeError::BadHeader("empty tile"));
        }
        if header.width > MAX_SIDE || header.height > MAX_SIDE {
            return Err(DecodeError::BadHeader(
                "tile side above the decoder's limit",
            ));
        }
        if !(header.quantum_m.is_finite() && header.quantum_m > 0.0 && header.offset_m.is_finite())
        {
            return Err(DecodeError::BadHeader(
                "quantum or offset is not a usable number",
            ));
        }
        if header.min > header.max {
            return Err(DecodeError::BadHeader("minimum above maximum"));
        }
        Ok(header)
    }
}

/// Why a frame without a stated size did not fit its plane.
#[cfg(not(target_arch = "wasm32"))]
enum Unsized {
    PastTile,
    Zstd(std::io::Error),
}

/// Decompresses one frame into `plane`, returning the bytes written; stops with
/// [`Unsized::PastTile`] at the first byte beyond it.
#[cfg(not(target_arch = "wasm32"))]
fn decompress_unsized(frame: &[u8], plane: &mut [u8]) -> Result<usize, Unsized> {
    use std::io::Read as _;
    let mut decoder = zstd::stream::read::Decoder::with_buffer(frame)
        .map_err(Unsized::Zstd)?
        .single_frame();
    // The window a streamed frame asks for is memory the decoder allocates: no larger than
    // the plane, or 8 MiB, the window of zstd's levels up to 19 (a smaller limit would
    // refuse frames that plain streaming compressors write).
    let window_log = plane.len().next_power_of_two().trailing_zeros().max(23);
    decoder.window_log_max(window_log).map_err(Unsized::Zstd)?;
    let mut written = 0;
    while written < plane.len() {
        match decoder.read(&mut plane[written..]).map_err(Unsized::Zstd)? {
            0 => return Ok(written),
            read => written += read,
        }
    }
    let mut beyond = [0u8; 1];
    match decoder.read(&mut beyond).map_err(Unsized::Zstd)? {
        0 => Ok(written),
        _ => Err(Unsized::PastTile),
    }
}

/// The zig-zag map of signed residuals to unsigned ones (0, -1, 1, -2, ... to 0, 1, 2, ...),
/// and back; the rANS coder's table steps use it too.
pub(crate) fn zigzag_encode(v: i32) -> u32 {
    ((v << 1) ^ (v >> 31)) as u32
}

pub(crate) fn zigzag_decode(z: u32) -> i32 {
    ((z >> 1) as i32) ^ -((z & 1) as i32)
}

fn planes_needed(largest: u32) -> usize {
    match largest {
        0..=0xff => 1,
        0x100..=0xffff => 2,
        0x1_0000..=0xff_ffff => 3,
        _ => 4,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn tile(width: u16, height: u16, mut f: impl FnMut(usize, usize) -> i32) -> Heights {
        let mut codes = Vec::new();
        for y in 0..usize::from(height) {
            for x in 0..usize::from(width) {
                codes.push(f(x, y));
            }
        }
        Heights {
            width,
            height,
            quantum_m: 0.1,
            offset_m: -5.0,
            codes,
        }
    }

    const CODERS: [Coder; 2] = [Coder::Rans, Coder::Zstd(3)];

    fn check_round_trip(h: &Heights) {
        for coder in CODERS {
            let bytes = h.encode_with(coder).expect("encodes");
            assert_eq!(Heights::decode(&bytes).expect("decodes"), *h, "{coder:?}");
        }
    }

    /// Codec version 1 as the browser build reads it (ruzstd): the same codes as zstd's
    /// own decoder gives, and the same refusals.
    fn decode_in_rust(bytes: &[u8]) -> Result<Vec<i32>, DecodeError> {
        let header = Header::parse(bytes)?;
        let mut codes = vec![0i32; usize::from(header.width) * usize::from(header.height)];
        decode_planes_in_rust(&header, &bytes[HEADER_LEN..], &mut codes)?;
        Ok(codes.iter().map(|c| c.wrapping_add(header.min)).collect())
    }

    #[test]
    fn the_browser_builds_reading_of_version_1_gives_zstds_codes_and_refusals() {
        let tiles = [
            tile(1, 1, |_, _| 7),
            tile(129, 129, |x, y| (x * 3 + y * 5) as i32),
            tile(65, 65, |x, y| {
                ((x * 7919 + y * 104_729) % 65536) as i32 - 32768
            }),
            tile(
                17,
                9,
                |x, y| if (x + y) % 2 == 0 { i32::MIN } else { i32::MAX },
            ),
        ];
        for h in &tiles {
            for level in [1, 3, 19] {
                let bytes = h.encode_with(Coder::Zstd(level)).expect("encodes");
                assert_eq!(
                    decode_in_rust(&bytes).expect("decodes"),
                    Heights::decode(&bytes).expect("decodes").codes,
                    "{}x{} at level {level}",
                    h.width,
                    h.height
                );
            }
        }
        let bomb = vec![0u8; 10_000];
        for frame in [
            zstd::bulk::compress(&bomb, 3).expect("compresses"),
            zstd::stream::encode_all(&bomb[..], 3).expect("compresses"),
        ] {
            let refused = decode_in_rust(&sealed(1, 4, &frame));
            assert!(
                matches!(
                    refused,
                    Err(DecodeError::PlanePastTile {
                        plane: 0,
                        allowed: 16,
                        ..
                    })
                ),
                "{refused:?}"
            );
        }
        let mut two = zstd::bulk::compress(&[0u8; 16], 3).expect("compresses");
        two.extend_from_slice(&[0u8; 3]);
        assert!(
            decode_in_rust(&sealed(1, 4, &two)).is_err(),
            "bytes after the last plane"
        );
    }

    #[test]
    fn planes_and_extremes_round_trip() {
        check_round_trip(&tile(1, 1, |_, _| 7));
        check_round_trip(&tile(129, 129, |x, y| (x * 3 + y * 5) as i32)); // a plane: residuals 0
        check_round_trip(&tile(17, 9, |x, y| {
            if (x + y) % 2 == 0 { i32::MIN } else { i32::MAX }
        }));
        check_round_trip(&tile(33, 33, |x, y| {
            ((x * 7919 + y * 104729) % 65536) as i32 - 32768
        }));
    }

    /// Under 0.006 bytes per sample: the residuals are 0 but along the first row and column
    /// (rANS spends a bit on each of the column's, which its contexts share with zeros).
    #[test]
    fn a_plane_compresses_to_almost_nothing() {
        let h = tile(129, 129, |x, y| 1000 + (x * 3 + y * 5) as i32);
        for coder in CODERS {
            let bytes = h.encode_with(coder).expect("encodes");
            assert!(
                bytes.len() < HEADER_LEN + 96,
                "{} bytes for a plane with {coder:?}",
                bytes.len()
            );
        }
    }

    #[test]
    fn the_default_coder_is_version_2_and_version_1_is_still_read() {
        let h = tile(65, 65, |x, y| ((x * x + 7 * y * y) % 3000) as i32);
        let v2 = h.encode().expect("encodes");
        assert_eq!(v2[4], CODEC_VERSION);
        let v1 = h.encode_with_level(19).expect("encodes");
        assert_eq!(v1[4], ZSTD_CODEC_VERSION);
        assert_eq!(Heights::decode(&v1).expect("version 1 decodes"), h);
        assert_eq!(Heights::decode(&v2).expect("version 2 decodes"), h);
        assert_eq!(Coder::Rans.name(), CODEC_NAME);
        assert_eq!(Coder::Zstd(19).name(), ZSTD_CODEC_NAME);
    }

    /// Rough terrain with a residual distribution like a DEM's: rANS with contexts beats
    /// zstd on the byte planes.
    #[test]
    fn rans_is_smaller_than_zstd_on_rough_terrain() {
        let mut state = 7u64;
        let mut noise = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((state >> 33) % 41) as i32 - 20
        };
        let mut codes = vec![0i32; 129 * 129];
        for y in 0..129 {
            for x in 0..129 {
                // Smooth slopes whose roughness grows eastwards, plus noise scaled by it.
                let rough = 1 + x as i32 / 16;
                codes[y * 129 + x] = ((x * 13 + y * 7) as f64 * (1.0 + (y as f64 / 9.0).sin()))
                    as i32
                    + noise() * rough;
            }
        }
        let h = Heights {
            width: 129,
            height: 129,
            quantum_m: 1.0,
            offset_m: 0.0,
            codes,
        };
        let rans = h.encode().expect("encodes").len();
        let zstd = h.encode_with_level(19).expect("encodes").len();
        assert!(rans < zstd, "rANS {rans} bytes, zstd {zstd}");
    }

    #[test]
    fn every_truncation_and_every_single_bit_flip_is_rejected() {
        let h = tile(33, 33, |x, y| ((x * x + 3 * y) % 500) as i32);
        for coder in CODERS {
            let bytes = h.encode_with(coder).expect("encodes");
            for len in 0..bytes.len() {
                assert!(
                    Heights::decode(&bytes[..len]).is_err(),
                    "{coder:?} truncated to {len} bytes"
                );
            }
            for bit in 0..bytes.len() * 8 {
                let mut corrupt = bytes.clone();
                corrupt[bit / 8] ^= 1 << (bit % 8);
                assert!(
                    Heights::decode(&corrupt).is_err(),
                    "{coder:?} bit {bit} flipped"
                );
            }
        }
    }

    /// Version 2's own checks, under a checksum that is right: every corrupt payload is an
    /// error, not a panic and not a wrong tile.
    #[test]
    fn corrupt_rans_payloads_behind_a_good_checksum_are_errors() {
        let h = tile(33, 33, |x, y| ((x * x + 3 * y) % 500) as i32);
        let bytes = h.encode().expect("encodes");
        let payload = &bytes[HEADER_LEN..];
        let mut caught = 0;
        for bit in 0..payload.len() * 8 {
            let mut corrupt = payload.to_vec();
            corrupt[bit / 8] ^= 1 << (bit % 8);
            match Heights::decode(&sealed_v(CODEC_VERSION, 0, 33, (0, 500), &corrupt)) {
                Err(_) => caught += 1,
                // A flip can yield another valid stream; then it must not claim this tile.
                Ok(other) => assert_ne!(other.codes, h.codes, "bit {bit}"),
            }
        }
        assert!(
            caught * 10 >= payload.len() * 8 * 9,
            "{caught} of {} caught",
            payload.len() * 8
        );
        for len in 0..payload.len() {
            assert!(
                Heights::decode(&sealed_v(CODEC_VERSION, 0, 33, (0, 500), &payload[..len]))
                    .is_err(),
                "payload cut to {len} bytes"
            );
        }
    }

    /// The checks at the end of a version-2 stream, each on its own: a valid stream with a
    /// word too many, a raw byte too many, or a start state changed is refused by name.
    #[test]
    fn a_rans_stream_that_does_not_end_cleanly_is_refused_by_name() {
        let h = tile(33, 33, |x, y| ((x * x + 3 * y) % 500) as i32);
        let bytes = h.encode().expect("encodes");
        let payload = &bytes[HEADER_LEN..];
        let u32_at = |i: usize| u32::from_le_bytes(payload[i..i + 4].try_into().expect("4"));
        let (table_len, raw_len) = (u32_at(0) as usize, u32_at(4) as usize);
        let decode = |payload: &[u8]| {
            Heights::decode(&sealed_v(
                CODEC_VERSION,
                0,
                33,
                (h.code_range().0, h.code_range().1),
                payload,
            ))
        };
        assert_eq!(decode(payload).expect("the stream as made").codes, h.codes);

        let mut extra_word = payload.to_vec();
        extra_word.extend_from_slice(&[0, 0]);
        let message = decode(&extra_word)
            .expect_err("a word too many")
            .to_string();
        assert!(message.contains("rANS words left over"), "{message}");

        let mut extra_raw = payload.to_vec();
        extra_raw[4..8].copy_from_slice(&(raw_len as u32 + 1).to_le_bytes());
        extra_raw.insert(8 + table_len + raw_len, 0);
        let message = decode(&extra_raw)
            .expect_err("a raw byte too many")
            .to_string();
        assert!(message.contains("raw bits left over"), "{message}");

        // A start state changed in one bit: the stream is refused, and for some such flip it
        // decodes to its end with the same words read, where only the final states tell.
        let words_at = 8 + table_len + raw_len;
        let mut final_state_caught = false;
        for bit in 0..8 * 16 {
            let mut state_off = payload.to_vec();
            state_off[words_at + bit / 8] ^= 1 << (bit % 8);
            let message = decode(&state_off)
                .expect_err("a start state changed")
                .to_string();
            final_state_caught |= message.contains("do not end where they began");
        }
        assert!(
            final_state_caught,
            "no flip of a start state reached the final check"
        );
    }

    fn sealed(planes: u8, side: u16, payload: &[u8]) -> Vec<u8> {
        sealed_v(ZSTD_CODEC_VERSION, planes, side, (0, 100), payload)
    }

    /// A tile whose header passes every check before the payload: magic, version, length and
    /// checksum are right; `planes`, the side, the range and the payload are whatever the
    /// test says.
    fn sealed_v(version: u8, planes: u8, side: u16, range: (i32, i32), payload: &[u8]) -> Vec<u8> {
        let mut bytes = Vec::new();
        bytes.extend_from_slice(&MAGIC);
        bytes.push(version);
        bytes.push(planes);
        bytes.extend_from_slice(&0u16.to_le_bytes());
        bytes.extend_from_slice(&side.to_le_bytes());
        bytes.extend_from_slice(&side.to_le_bytes());
        bytes.extend_from_slice(&1.0f64.to_le_bytes());
        bytes.extend_from_slice(&0.0f64.to_le_bytes());
        bytes.extend_from_slice(&range.0.to_le_bytes());
        bytes.extend_from_slice(&range.1.to_le_bytes());
        bytes.extend_from_slice(&(payload.len() as u32).to_le_bytes());
        let mut crc = crc32fast::Hasher::new();
        crc.update(&bytes);
        crc.update(payload);
        bytes.extend_from_slice(&crc.finalize().to_le_bytes());
        bytes.extend_from_slice(payload);
        bytes
    }

    #[test]
    fn a_plane_that_decompresses_past_the_tile_names_both_sizes() {
        let bomb = vec![0u8; 10_000];
        let check = |frame: &[u8], message: &str| {
            let error = Heights::decode(&sealed(1, 4, frame)).expect_err("a 10 kB plane");
            assert_eq!(error.to_string(), message);
        };
        // A frame that states its size is refused before it is decompressed.
        check(
            &zstd::bulk::compress(&bomb, 3).expect("compresses"),
            "heights plane 0 says it decompresses to 10000 bytes, more than the 16 bytes of a \
             4x4 tile",
        );
        // A streamed frame states none: decompression stops where the tile ends.
        check(
            &zstd::stream::encode_all(&bomb[..], 3).expect("compresses"),
            "heights plane 0 decompresses past the 16 bytes of a 4x4 tile (its frame does not \
             state its size)",
        );
    }

    #[test]
    fn bad_inputs_to_the_encoder_are_errors() {
        let mut h = tile(4, 4, |_, _| 0);
        h.codes.pop();
        assert!(matches!(h.encode(), Err(EncodeError::WrongLength { .. })));
        let mut h = tile(4, 4, |_, _| 0);
        h.quantum_m = 0.0;
        assert_eq!(h.encode(), Err(EncodeError::BadQuantum(0.0)));
        assert!(matches!(
            tile(0, 4, |_, _| 0).encode(),
            Err(EncodeError::BadSize { .. })
        ));
    }

    proptest! {
        #[test]
        fn random_tiles_round_trip(
            width in 1u16..40, height in 1u16..40, seed in any::<u64>(), amplitude in 0i64..=(1 << 31)
        ) {
            // A deterministic pseudo-random surface from the seed (SplitMix64 steps).
            let mut state = seed;
            let h = tile(width, height, |_, _| {
                state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
                let mut z = state;
                z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
                z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
                ((z >> 33) as i64 % (amplitude + 1)) as i32
            });
            for coder in CODERS {
                let bytes = h.encode_with(coder).expect("encodes");
                prop_assert_eq!(&Heights::decode(&bytes).expect("decodes"), &h);
            }
        }

        #[test]
        fn arbitrary_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..200)) {
            let _ = Heights::decode(&bytes);
        }

        #[test]
        fn arbitrary_bytes_behind_a_valid_header_never_panic(
            tail in proptest::collection::vec(any::<u8>(), 0..300), planes in 0u8..6, side in 0u16..300
        ) {
            // Headers that pass the checksum but lie about everything else.
            let bytes = sealed(planes, side, &tail);
            prop_assert!(Heights::decode(&bytes).is_err());
        }

        #[test]
        fn arbitrary_rans_payloads_never_panic(
            tail in proptest::collection::vec(any::<u8>(), 0..400), side in 1u16..40, top in 0i32..1000
        ) {
            // Version 2 streams: lengths, tables and words all made up; whatever decodes
            // must still be a tile of the header's size and range.
            let bytes = sealed_v(CODEC_VERSION, 0, side, (0, top), &tail);
            if let Ok(h) = Heights::decode(&bytes) {
                prop_assert_eq!(h.codes.len(), usize::from(side) * usize::from(side));
                prop_assert_eq!(h.code_range(), (0, top));
            }
        }

        #[test]
        fn shaped_rans_payloads_never_panic(
            table in proptest::collection::vec(any::<u8>(), 0..64),
            raw in proptest::collection::vec(any::<u8>(), 0..64),
            words in proptest::collection::vec(any::<u8>(), 8..200),
            side in 1u16..30,
        ) {
            // The section lengths right, so the tables, bits and words are what is tried.
            let mut payload = Vec::new();
            payload.extend_from_slice(&(table.len() as u32).to_le_bytes());
            payload.extend_from_slice(&(raw.len() as u32).to_le_bytes());
            payload.extend_from_slice(&table);
            payload.extend_from_slice(&raw);
            payload.extend_from_slice(&words[..words.len() & !1]);
            let _ = Heights::decode(&sealed_v(CODEC_VERSION, 0, side, (0, 100), &payload));
        }
    }
}
