//! What a tile's samples are on the GPU: 16-bit height codes, two a 32-bit word, relative to
//! a code base of the tile's own ([`pack_codes`]). The shader turns them back into metres
//! with the tile's quantum and offset, and computes each sample's normal from its neighbours
//! (`terrain.wgsl`): 2 bytes a sample, where a height and a packed normal took 8.
//!
//! A tile whose codes span more than 65,535 quanta cannot keep every code in 16 bits: it is
//! drawn at a coarser quantum, `2^shift` codes, the smallest that fits (each code rounded to
//! the nearest multiple of `2^shift`, at most `2^(shift - 1)` quanta off). Its base is a
//! multiple of `2^shift`, so two such tiles with the same shift round a shared border
//! sample alike.

use terrain_shared::Heights;

/// A tile's samples packed for the GPU. See the module documentation.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TileCodes {
    /// Two samples a word, the even sample (row-major) in the low 16 bits.
    pub words: Vec<u32>,
    /// Code of bits 0.
    pub base: i32,
    /// Sample `i`'s code is `base + (bits_i << shift)`.
    pub shift: u32,
}

impl TileCodes {
    /// The code sample `i` is drawn with.
    pub fn code(&self, i: usize) -> i64 {
        let bits = (self.words[i / 2] >> (16 * (i % 2))) & 0xffff;
        i64::from(self.base) + (i64::from(bits) << self.shift)
    }
}

/// Words of a tile of `samples` samples.
pub fn words_for(samples: u64) -> u64 {
    samples.div_ceil(2)
}

/// Packs `heights`' codes. See the module documentation.
pub fn pack_codes(heights: &Heights) -> TileCodes {
    let (lo, hi) = heights.code_range();
    let (lo, hi) = (i64::from(lo), i64::from(hi));
    let mut shift = 0u32;
    let base = |shift: u32| lo.div_euclid(1 << shift) << shift;
    // The largest code, rounded to its nearest multiple of 2^shift, must fit in 16 bits.
    while ((hi - base(shift) + ((1i64 << shift) >> 1)) >> shift) > 0xffff {
        shift += 1;
    }
    let b = base(shift);
    let bits = |code: i32| -> u32 {
        let rounded = (i64::from(code) - b + ((1i64 << shift) >> 1)) >> shift;
        rounded.clamp(0, 0xffff) as u32
    };
    let words = heights
        .codes
        .chunks(2)
        .map(|pair| bits(pair[0]) | pair.get(1).map_or(0, |&c| bits(c) << 16))
        .collect();
    TileCodes {
        words,
        // The base of a tile of codes a 32-bit code holds fits too: it is the smallest code,
        // rounded down to a multiple of 2^shift with shift < 17.
        base: i32::try_from(b).unwrap_or(i32::MIN),
        shift,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn tile(codes: Vec<i32>) -> Heights {
        let n = (codes.len() as f64).sqrt() as u16;
        Heights {
            width: n,
            height: n,
            quantum_m: 0.01,
            offset_m: -100.0,
            codes,
        }
    }

    #[test]
    fn codes_within_16_bits_of_each_other_come_back_exactly() {
        let codes: Vec<i32> = (0..9).map(|i| -40_000 + i * 8_000).collect();
        let packed = pack_codes(&tile(codes.clone()));
        assert_eq!(packed.shift, 0);
        assert_eq!(packed.base, -40_000);
        assert_eq!(packed.words.len(), 5, "9 samples, two a word");
        for (i, &c) in codes.iter().enumerate() {
            assert_eq!(packed.code(i), i64::from(c));
        }
    }

    #[test]
    fn a_tile_wider_than_16_bits_takes_the_smallest_shift_and_rounds_to_nearest() {
        // A span of 200,000 quanta needs 18 bits: shift 2, each code within 2 quanta.
        let codes = vec![5, 200_005, 100_002, 7, 99_999, 1, 2, 3, 150_001];
        let packed = pack_codes(&tile(codes.clone()));
        assert_eq!(packed.shift, 2);
        assert_eq!(packed.base % 4, 0);
        for (i, &c) in codes.iter().enumerate() {
            assert!((packed.code(i) - i64::from(c)).abs() <= 2, "sample {i}");
        }
    }

    proptest! {
        /// Any tile: every code comes back within 2^(shift-1) quanta (exactly when the
        /// codes fit in 16 bits), and two tiles of the same shift draw a shared code alike.
        #[test]
        fn every_code_comes_back_within_half_a_step(
            codes in proptest::collection::vec(-3_000_000i32..3_000_000, 9),
            shared in -3_000_000i32..3_000_000,
        ) {
            let mut a = codes.clone();
            a[8] = shared;
            let pa = pack_codes(&tile(a.clone()));
            let half = (1i64 << pa.shift) >> 1;
            for (i, &c) in a.iter().enumerate() {
                prop_assert!((pa.code(i) - i64::from(c)).abs() <= half);
            }
            let (lo, hi) = tile(a.clone()).code_range();
            if i64::from(hi) - i64::from(lo) <= 0xffff {
                prop_assert_eq!(pa.shift, 0);
            }
            let mut b: Vec<i32> = codes.iter().map(|c| c / 2).collect();
            b[0] = shared;
            let pb = pack_codes(&tile(b));
            if pb.shift == pa.shift {
                prop_assert_eq!(pb.code(0), pa.code(8));
            }
        }
    }
}
