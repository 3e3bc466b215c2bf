//! The web tiles' index, at the end of `web.pack`: per tile its kind, coordinates, size and
//! hash, in the pack's order (offsets are the running sum of the sizes, never stored).
//!
//! Layout (little-endian): magic `TWEB`, version 1, a u32 count, then per tile: kind u8,
//! zoom u8, x u32, y u32, size u32, hash 16 bytes (30 bytes a tile).

use terrain_shared::manifest::Blob;
use thiserror::Error;

const MAGIC: &[u8; 4] = b"TWEB";
const VERSION: u8 = 1;
const HEADER: usize = 9;
const ENTRY: usize = 30;

/// What a web tile is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Kind {
    /// Heights as Terrarium PNG (XYZ).
    Terrarium = 0,
    /// Heights as Mapbox Terrain-RGB PNG (XYZ).
    TerrainRgb = 1,
    /// The texture as RGBA PNG (XYZ).
    Texture = 2,
    /// A gzipped quantized-mesh-1.0 tile (geographic scheme, TMS rows).
    QuantizedMesh = 3,
}

impl Kind {
    fn from_u8(v: u8) -> Option<Kind> {
        Some(match v {
            0 => Kind::Terrarium,
            1 => Kind::TerrainRgb,
            2 => Kind::Texture,
            3 => Kind::QuantizedMesh,
            _ => return None,
        })
    }
}

/// One tile's place in the index.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct Entry {
    pub kind: Kind,
    pub z: u32,
    pub x: u32,
    pub y: u32,
}

#[derive(Debug, Error, PartialEq, Eq)]
pub enum IndexError {
    #[error("web index of {0} bytes is too short")]
    Short(usize),
    #[error("not a web index (magic {0:02x?})")]
    Magic([u8; 4]),
    #[error("web index version {0} is not supported (this build reads {VERSION})")]
    Version(u8),
    #[error("web index says {count} tiles in {bytes} bytes")]
    Length { count: usize, bytes: usize },
    #[error("web index entry {0} is not a tile kind this build knows")]
    BadEntry(usize),
}

/// The index of `entries`, in order.
pub fn encode(entries: &[(Entry, Blob)]) -> Vec<u8> {
    let mut out = Vec::with_capacity(HEADER + ENTRY * entries.len());
    out.extend_from_slice(MAGIC);
    out.push(VERSION);
    out.extend_from_slice(&(entries.len() as u32).to_le_bytes());
    for (e, blob) in entries {
        out.push(e.kind as u8);
        out.push(e.z as u8);
        out.extend_from_slice(&e.x.to_le_bytes());
        out.extend_from_slice(&e.y.to_le_bytes());
        out.extend_from_slice(&(blob.bytes as u32).to_le_bytes());
        let hash: Vec<u8> = (0..16)
            .map(|i| {
                u8::from_str_radix(blob.hash.get(2 * i..2 * i + 2).unwrap_or("00"), 16).unwrap_or(0)
            })
            .collect();
        out.extend_from_slice(&hash);
    }
    out
}

/// The entries of an index, with each tile's size and hash. Never panics.
pub fn decode(bytes: &[u8]) -> Result<Vec<(Entry, Blob)>, IndexError> {
    let head = bytes.get(..HEADER).ok_or(IndexError::Short(bytes.len()))?;
    let magic = [head[0], head[1], head[2], head[3]];
    if &magic != MAGIC {
        return Err(IndexError::Magic(magic));
    }
    if head[4] != VERSION {
        return Err(IndexError::Version(head[4]));
    }
    let count = u32::from_le_bytes([head[5], head[6], head[7], head[8]]) as usize;
    if count.checked_mul(ENTRY).and_then(|n| n.checked_add(HEADER)) != Some(bytes.len()) {
        return Err(IndexError::Length {
            count,
            bytes: bytes.len(),
        });
    }
    let u32_at = |b: &[u8], at: usize| u32::from_le_bytes([b[at], b[at + 1], b[at + 2], b[at + 3]]);
    bytes[HEADER..]
        .chunks_exact(ENTRY)
        .enumerate()
        .map(|(i, e)| {
            let kind = Kind::from_u8(e[0]).ok_or(IndexError::BadEntry(i))?;
            let hash = e[14..30].iter().map(|b| format!("{b:02x}")).collect();
            Ok((
                Entry {
                    kind,
                    z: u32::from(e[1]),
                    x: u32_at(e, 2),
                    y: u32_at(e, 6),
                },
                Blob {
                    hash,
                    bytes: u64::from(u32_at(e, 10)),
                },
            ))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_index_round_trips_and_refuses_any_truncation() {
        let entries = vec![
            (
                Entry {
                    kind: Kind::Terrarium,
                    z: 3,
                    x: 2,
                    y: 5,
                },
                Blob::of(b"one"),
            ),
            (
                Entry {
                    kind: Kind::QuantizedMesh,
                    z: 12,
                    x: 4000,
                    y: 1999,
                },
                Blob::of(b"two!"),
            ),
        ];
        let bytes = encode(&entries);
        assert_eq!(decode(&bytes), Ok(entries));
        for cut in 0..bytes.len() {
            assert!(decode(&bytes[..cut]).is_err(), "cut at {cut}");
        }
        let mut bad = bytes.clone();
        bad[HEADER] = 9;
        assert_eq!(decode(&bad), Err(IndexError::BadEntry(0)));
    }
}
