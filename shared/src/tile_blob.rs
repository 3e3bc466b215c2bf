//! The tile blob (`terrain-tile/1`): what `GET …/heights` returns. It carries what a client
//! needs only once it holds the tile, so the manifest stays a few bytes a tile:
//!
//! - the per-strip-mask errors (metres, against the full-resolution surface),
//! - the hash and size of each texture level, so every texture body is verified against a
//!   hash that came, through this blob's own hash, from the manifest,
//! - the heights, in the heights codec ([`crate::heights`]).
//!
//! Little-endian layout:
//!
//! | bytes | field |
//! |---|---|
//! | 4 | magic `TTIL` |
//! | 1 | version, 1 |
//! | 1 | reserved, 0 |
//! | 2 | mask levels `m` |
//! | 2 | texture levels `t` |
//! | 2 | reserved, 0 |
//! | 4 | heights length `h` |
//! | 4 `m` | mask errors, `f32` metres, index 0 first |
//! | 20 `t` | per texture level, coarsest first: 16-byte hash, `u32` size |
//! | `h` | the heights blob |
//!
//! Nothing may follow. [`TileBlob::decode`] returns an error for any other input and never
//! panics; it does not decode the heights (that is [`crate::Heights::decode`]'s job).

use crate::manifest::Blob;
use thiserror::Error;

pub const MAGIC: [u8; 4] = *b"TTIL";
pub const VERSION: u8 = 1;
/// Name and version of this container, as the manifest's `heights.container`.
pub const CONTAINER_NAME: &str = "terrain-tile/1";
const HEADER: usize = 16;
/// More mask or texture levels than any tile of `MAX_SIDE` samples has.
const MAX_LEVELS: usize = 1 << 14;

/// A tile blob, split into its parts.
#[derive(Debug, Clone, PartialEq)]
pub struct TileBlob {
    /// Per strip-mask level, the largest vertical error of that mask against the
    /// full-resolution surface the tile stands for, metres (index 0: the tile itself).
    pub mask_errors_m: Vec<f32>,
    /// Hash and size of each texture level, coarsest first.
    pub texture: Vec<Blob>,
    /// The heights blob ([`crate::heights`]), not yet decoded.
    pub heights: Vec<u8>,
}

#[derive(Debug, Error, PartialEq, Eq)]
pub enum TileBlobError {
    #[error("tile blob of {0} bytes is shorter than its {HEADER}-byte header")]
    Short(usize),
    #[error("not a tile blob (magic {0:02x?})")]
    Magic([u8; 4]),
    #[error("tile blob version {0} is not supported (this build reads {VERSION})")]
    Version(u8),
    #[error("tile blob says {mask} mask and {texture} texture levels, more than a tile has")]
    TooManyLevels { mask: usize, texture: usize },
    #[error("tile blob is {found} bytes; its header says {expected}")]
    Length { found: usize, expected: usize },
    #[error("tile blob has a mask error that is not a finite, non-negative number")]
    BadError,
}

impl TileBlob {
    /// The blob's bytes.
    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(
            HEADER + 4 * self.mask_errors_m.len() + 20 * self.texture.len() + self.heights.len(),
        );
        out.extend_from_slice(&MAGIC);
        out.push(VERSION);
        out.push(0);
        out.extend_from_slice(&(self.mask_errors_m.len() as u16).to_le_bytes());
        out.extend_from_slice(&(self.texture.len() as u16).to_le_bytes());
        out.extend_from_slice(&[0, 0]);
        out.extend_from_slice(&(self.heights.len() as u32).to_le_bytes());
        for e in &self.mask_errors_m {
            out.extend_from_slice(&e.to_le_bytes());
        }
        for blob in &self.texture {
            out.extend_from_slice(&hash_bytes(&blob.hash));
            out.extend_from_slice(&(blob.bytes as u32).to_le_bytes());
        }
        out.extend_from_slice(&self.heights);
        out
    }

    /// Splits a blob into its parts, checking every size.
    pub fn decode(bytes: &[u8]) -> Result<TileBlob, TileBlobError> {
        let head = TileBlob::head(bytes)?;
        Ok(TileBlob {
            mask_errors_m: head.mask_errors_m,
            texture: head.texture,
            heights: bytes[head.heights_at..].to_vec(),
        })
    }

    /// The blob's parts before the heights, and where the heights start: what a server
    /// needs to locate the textures without copying the heights.
    pub fn head(bytes: &[u8]) -> Result<TileHead, TileBlobError> {
        let header: &[u8; HEADER] = bytes
            .get(..HEADER)
            .and_then(|h| h.try_into().ok())
            .ok_or(TileBlobError::Short(bytes.len()))?;
        let magic = [header[0], header[1], header[2], header[3]];
        if magic != MAGIC {
            return Err(TileBlobError::Magic(magic));
        }
        if header[4] != VERSION {
            return Err(TileBlobError::Version(header[4]));
        }
        let mask = usize::from(u16::from_le_bytes([header[6], header[7]]));
        let texture = usize::from(u16::from_le_bytes([header[8], header[9]]));
        if mask > MAX_LEVELS || texture > 32 {
            return Err(TileBlobError::TooManyLevels { mask, texture });
        }
        let heights = u32::from_le_bytes([header[12], header[13], header[14], header[15]]) as usize;
        let expected = HEADER + 4 * mask + 20 * texture + heights;
        if bytes.len() != expected {
            return Err(TileBlobError::Length {
                found: bytes.len(),
                expected,
            });
        }
        let mut at = HEADER;
        let mut mask_errors_m = Vec::with_capacity(mask);
        for _ in 0..mask {
            let e = f32::from_le_bytes([bytes[at], bytes[at + 1], bytes[at + 2], bytes[at + 3]]);
            if !(e.is_finite() && e >= 0.0) {
                return Err(TileBlobError::BadError);
            }
            mask_errors_m.push(e);
            at += 4;
        }
        let mut levels = Vec::with_capacity(texture);
        for _ in 0..texture {
            let hash: String = bytes[at..at + 16]
                .iter()
                .map(|b| format!("{b:02x}"))
                .collect();
            let size = u32::from_le_bytes([
                bytes[at + 16],
                bytes[at + 17],
                bytes[at + 18],
                bytes[at + 19],
            ]);
            levels.push(Blob {
                hash,
                bytes: u64::from(size),
            });
            at += 20;
        }
        Ok(TileHead {
            mask_errors_m,
            texture: levels,
            heights_at: at,
        })
    }
}

/// A tile blob's header and tables ([`TileBlob::head`]).
#[derive(Debug, Clone, PartialEq)]
pub struct TileHead {
    pub mask_errors_m: Vec<f32>,
    pub texture: Vec<Blob>,
    /// Offset of the heights blob; it runs to the end.
    pub heights_at: usize,
}

/// The 16 bytes of a 32-digit hex hash (zeros for anything else: `Blob` hashes are always
/// [`crate::manifest::content_hash`]es).
fn hash_bytes(hex: &str) -> [u8; 16] {
    let mut out = [0u8; 16];
    for (i, byte) in out.iter_mut().enumerate() {
        *byte = hex
            .get(2 * i..2 * i + 2)
            .and_then(|pair| u8::from_str_radix(pair, 16).ok())
            .unwrap_or(0);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> TileBlob {
        TileBlob {
            mask_errors_m: vec![0.0, 0.5, 1.25],
            texture: vec![Blob::of(b"coarse"), Blob::of(b"finer level")],
            heights: b"THGT and the rest".to_vec(),
        }
    }

    #[test]
    fn blobs_round_trip() {
        let blob = sample();
        assert_eq!(TileBlob::decode(&blob.encode()).expect("decodes"), blob);
    }

    #[test]
    fn every_truncation_and_every_extension_is_refused() {
        let bytes = sample().encode();
        for len in 0..bytes.len() {
            assert!(TileBlob::decode(&bytes[..len]).is_err(), "{len} bytes");
        }
        let mut longer = bytes.clone();
        longer.push(0);
        assert!(matches!(
            TileBlob::decode(&longer),
            Err(TileBlobError::Length { .. })
        ));
    }

    /// `bytes` with the header's reserved bytes zeroed: what encoding a decoded blob gives.
    fn canonical(bytes: &[u8]) -> Vec<u8> {
        let mut out = bytes.to_vec();
        for i in [5, 10, 11] {
            if let Some(b) = out.get_mut(i) {
                *b = 0;
            }
        }
        out
    }

    proptest::proptest! {
        /// Any bytes: an error or a blob that encodes back to them, never a panic.
        #[test]
        fn any_bytes_decode_to_an_error_or_to_a_blob_that_encodes_back_to_them(
            bytes in proptest::collection::vec(proptest::num::u8::ANY, 0..160),
            magic in proptest::bool::ANY,
        ) {
            let mut bytes = bytes;
            if magic && bytes.len() >= HEADER {
                // Past the magic and version, with small counts and sizes, so that the
                // tables and lengths are what is tried.
                bytes[..4].copy_from_slice(&MAGIC);
                bytes[4] = VERSION;
                bytes[6] %= 4;
                bytes[7] = 0;
                bytes[8] %= 3;
                bytes[9] = 0;
                bytes[12] %= 64;
                bytes[13..16].fill(0);
            }
            if let Ok(blob) = TileBlob::decode(&bytes) {
                proptest::prop_assert_eq!(blob.encode(), canonical(&bytes));
                let head = TileBlob::head(&bytes).expect("decoded");
                proptest::prop_assert_eq!(&bytes[head.heights_at..], &blob.heights[..]);
            }
        }

        /// A valid blob with one byte changed: still an error or a blob, never a panic.
        #[test]
        fn a_blob_with_any_byte_changed_decodes_to_an_error_or_to_itself(
            at in 0usize..1000,
            value in proptest::num::u8::ANY,
        ) {
            let mut bytes = sample().encode();
            let at = at % bytes.len();
            bytes[at] = value;
            if let Ok(blob) = TileBlob::decode(&bytes) {
                proptest::prop_assert_eq!(blob.encode(), canonical(&bytes));
            }
        }
    }

    #[test]
    fn a_negative_or_nan_error_is_refused() {
        let mut blob = sample();
        blob.mask_errors_m[1] = f32::NAN;
        assert_eq!(
            TileBlob::decode(&blob.encode()),
            Err(TileBlobError::BadError)
        );
    }
}
