//! The entropy coder of heights codec 2: the planar predictor's residuals coded with rANS
//! under a context of the row above, with frequency tables made for each tile.
//!
//! - **Tokens.** A zig-zag residual `z` below 16 is its own token; a larger one is coded as
//!   its bit length and the two bits below its leading one (128 tokens in all, for any
//!   `u32`), the bits below those following raw in a separate bit stream. Terrain residuals
//!   are small and their distribution smooth, so the raw bits are nearly uniform.
//! - **Context.** The activity of sample `(x, y)` is a weighted sum of the zig-zag residuals
//!   of row `y - 1` at `x - 2 ..= x + 2` (weights 1, 2, 2, 2, 1), in [`CLASSES`]
//!   logarithmic classes; row 0 has a context of its own. It uses only the row above, so a
//!   decoder computes a whole row's contexts before it decodes the row's tokens, and the
//!   tokens decode without waiting for the heights they make.
//! - **Tables.** Each tile carries, per context it uses, the frequencies of its tokens,
//!   each as a step of a half-octave scale (`2^(q/2)`), the steps delta-coded with Elias
//!   gamma: a few dozen bytes per tile. Both sides turn the steps into frequencies summing
//!   to `2^PROB_BITS` with the same integer arithmetic ([`normalize`]).
//! - **rANS** with 32-bit states renormalised by 16-bit words, four states interleaved
//!   (sample `x` of a row takes state `x % 4`) so that consecutive tokens decode in
//!   parallel, and a decoder table per context that gives a state's token in one lookup.
//!   A row decodes in three passes: its tokens (rANS only, no branches), then their raw
//!   bits, then the heights and the next row's contexts.
//!
//! A decoder checks everything a hostile tile could get wrong: table syntax, a context
//! used without a table, a stream read past its end, states that do not end where the
//! encoder began, bytes left over. Every check is an error, never a panic.

use crate::heights::{zigzag_decode, zigzag_encode};

/// Probabilities are multiples of `2^-PROB_BITS`.
pub(crate) const PROB_BITS: u32 = 10;
const TOTAL: u32 = 1 << PROB_BITS;
const SLOT_MASK: u32 = TOTAL - 1;
/// Tokens of a zig-zag residual: 16 small values, then 4 per bit length from 4 to 31.
pub(crate) const TOKENS: usize = 128;
/// Activity classes of rows after the first.
pub(crate) const CLASSES: usize = 14;
/// The classes and the first row's context.
pub(crate) const CONTEXTS: usize = CLASSES + 1;
const FIRST_ROW: u8 = CLASSES as u8;
/// Entries of the decoder's tables: room for 16 contexts, so that a context masked to 4
/// bits indexes them without a bounds check.
const TABLES_LEN: usize = 16 << PROB_BITS;
const _: () = assert!(CONTEXTS <= 16);
/// Interleaved rANS states.
const STATES: usize = 4;
/// Lower bound of a rANS state.
const RANS_L: u32 = 1 << 16;
/// Largest frequency step; step 0 means "absent".
const Q_MAX: u32 = 31;
/// A residual above this counts as this much in an activity sum (which saturates the top
/// class long before), so the sum fits a `u32`.
const ACTIVITY_CLAMP: u32 = 1 << 20;

/// Weight of frequency step `q`: `16 * 2^((q - 1) / 2)` rounded, 0 for step 0.
const WEIGHTS: [u32; Q_MAX as usize + 1] = [
    0, 16, 23, 32, 45, 64, 91, 128, 181, 256, 362, 512, 724, 1024, 1448, 2048, 2896, 4096, 5793,
    8192, 11585, 16384, 23170, 32768, 46341, 65536, 92682, 131072, 185364, 262144, 370728, 524288,
];

/// What went wrong in a coded stream (the heights codec wraps it).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum StreamError {
    Table(&'static str),
    MissingTable(u8),
    Overrun(&'static str),
    BadEnd(&'static str),
}

impl std::fmt::Display for StreamError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            StreamError::Table(why) => write!(f, "bad frequency table: {why}"),
            StreamError::MissingTable(c) => write!(f, "context {c} is used but has no table"),
            StreamError::Overrun(what) => write!(f, "the {what} stream ends early"),
            StreamError::BadEnd(why) => write!(f, "the streams do not end cleanly: {why}"),
        }
    }
}

/// Token of a zig-zag residual, its raw bits' count and value.
#[inline]
fn token(z: u32) -> (u8, u32, u32) {
    if z < 16 {
        (z as u8, 0, 0)
    } else {
        let e = 31 - z.leading_zeros(); // 4..=31
        let mantissa = (z >> (e - 2)) & 3;
        let bits = e - 2;
        (
            (16 + (e - 4) * 4 + mantissa) as u8,
            bits,
            z & ((1 << bits) - 1),
        )
    }
}

/// Smallest residual of each token, and its raw bits.
const TOKEN_BASE: [u32; TOKENS] = {
    let mut base = [0u32; TOKENS];
    let mut t = 0;
    while t < TOKENS {
        base[t] = if t < 16 {
            t as u32
        } else {
            let e = ((t - 16) / 4 + 4) as u32;
            let mantissa = ((t - 16) % 4) as u32;
            (1 << e) | (mantissa << (e - 2))
        };
        t += 1;
    }
    base
};
const TOKEN_BITS: [u8; TOKENS] = {
    let mut bits = [0u8; TOKENS];
    let mut t = 16;
    while t < TOKENS {
        bits[t] = ((t - 16) / 4 + 2) as u8;
        t += 1;
    }
    bits
};

/// The contexts of a row from the zig-zag residuals of the row above, `None` for row 0.
/// `padded` is scratch of `above.len() + 4`.
fn row_contexts(above: Option<&[u32]>, padded: &mut Vec<u32>, out: &mut [u8]) {
    let Some(above) = above else {
        out.fill(FIRST_ROW);
        return;
    };
    let w = above.len();
    padded.clear();
    let first = above[0].min(ACTIVITY_CLAMP);
    let last = above[w - 1].min(ACTIVITY_CLAMP);
    padded.extend_from_slice(&[first, first]);
    padded.extend(above.iter().map(|&z| z.min(ACTIVITY_CLAMP)));
    padded.extend_from_slice(&[last, last]);
    // Five shifted views of one length, so the loop has no bounds checks and vectorises.
    let (p0, p1, p2, p3, p4) = (
        &padded[..w],
        &padded[1..w + 1],
        &padded[2..w + 2],
        &padded[3..w + 3],
        &padded[4..w + 4],
    );
    let out = &mut out[..w];
    for x in 0..w {
        out[x] = class(p0[x] + 2 * (p1[x] + p2[x] + p3[x]) + p4[x]);
    }
}

/// The class of an activity below 2^24: its bit length, at most `CLASSES - 1`. Read from
/// the exponent of the activity as an `f32` (exact below 2^24), which vectorises.
#[inline]
fn class(activity: u32) -> u8 {
    let exponent = ((activity as i32 as f32).to_bits() >> 23) as i32 - 126;
    exponent.clamp(0, CLASSES as i32 - 1) as u8
}

/// Frequencies summing to `TOTAL` from frequency steps, or `None` when every step is 0.
/// The encoder and the decoder both call it, so it is integer arithmetic only.
fn normalize(steps: &[u8]) -> Option<[u16; TOKENS]> {
    let sum: u64 = steps
        .iter()
        .map(|&q| u64::from(WEIGHTS[usize::from(q)]))
        .sum();
    if sum == 0 {
        return None;
    }
    let mut freq = [0u16; TOKENS];
    let mut total: i64 = 0;
    for (f, &q) in freq.iter_mut().zip(steps) {
        if q > 0 {
            let share = u64::from(WEIGHTS[usize::from(q)]) * u64::from(TOTAL) / sum;
            *f = share.max(1) as u16;
            total += i64::from(*f);
        }
    }
    let mut diff = i64::from(TOTAL) - total;
    let largest = |freq: &[u16; TOKENS]| {
        let mut best = 0;
        for (i, &f) in freq.iter().enumerate() {
            if f > freq[best] {
                best = i;
            }
        }
        best
    };
    if diff > 0 {
        let i = largest(&freq);
        freq[i] += diff as u16;
    }
    // At most TOKENS (< TOTAL) frequencies were raised to 1, so what is over can always be
    // taken from frequencies above 1, largest first.
    while diff < 0 {
        let i = largest(&freq);
        let take = (-diff).min(i64::from(freq[i]) - 1);
        freq[i] -= take as u16;
        diff += take;
    }
    Some(freq)
}

/// LSB-first bit writer.
#[derive(Default)]
struct BitWriter {
    bytes: Vec<u8>,
    acc: u64,
    count: u32,
}

impl BitWriter {
    #[inline]
    fn put(&mut self, value: u32, bits: u32) {
        debug_assert!(bits <= 32);
        self.acc |= u64::from(value) << self.count;
        self.count += bits;
        while self.count >= 8 {
            self.bytes.push(self.acc as u8);
            self.acc >>= 8;
            self.count -= 8;
        }
    }

    /// Elias gamma of `v >= 1`.
    fn gamma(&mut self, v: u32) {
        let n = 31 - v.leading_zeros();
        self.put(0, n);
        self.put(1, 1);
        self.put(v & ((1 << n) - 1), n);
    }

    fn finish(mut self) -> Vec<u8> {
        if self.count > 0 {
            self.bytes.push(self.acc as u8);
        }
        self.bytes
    }
}

/// LSB-first bit reader over a byte slice; reading past the end gives zeros and is
/// reported by [`BitReader::overrun`].
struct BitReader<'a> {
    bytes: &'a [u8],
    next: usize,
    acc: u64,
    count: u32,
    /// Bits handed out.
    consumed: u64,
}

impl<'a> BitReader<'a> {
    fn new(bytes: &'a [u8]) -> BitReader<'a> {
        BitReader {
            bytes,
            next: 0,
            acc: 0,
            count: 0,
            consumed: 0,
        }
    }

    #[inline]
    fn refill(&mut self) {
        if let Some(chunk) = self.bytes.get(self.next..self.next + 8) {
            let word = u64::from_le_bytes(chunk.try_into().expect("8 bytes"));
            self.acc |= word << self.count;
            let taken = (63 - self.count) / 8;
            self.next += taken as usize;
            self.count += taken * 8;
        } else {
            while self.count <= 56 {
                let byte = self.bytes.get(self.next).copied().unwrap_or(0);
                self.acc |= u64::from(byte) << self.count;
                self.next += 1;
                self.count += 8;
            }
        }
    }

    /// `bits <= 32` bits.
    #[inline]
    fn get(&mut self, bits: u32) -> u32 {
        if self.count < bits {
            self.refill();
        }
        let value = (self.acc & ((1u64 << bits) - 1)) as u32;
        self.acc >>= bits;
        self.count -= bits;
        self.consumed += u64::from(bits);
        value
    }

    fn gamma(&mut self) -> Result<u32, StreamError> {
        let mut n = 0;
        while self.get(1) == 0 {
            n += 1;
            if n > 16 {
                return Err(StreamError::Table("a step delta is too long"));
            }
        }
        Ok((1 << n) | self.get(n))
    }

    fn overrun(&self) -> bool {
        self.consumed > self.bytes.len() as u64 * 8
    }

    /// Whether every byte was read (the last one perhaps in part).
    fn used_exactly(&self) -> bool {
        self.consumed.div_ceil(8) == self.bytes.len() as u64
    }
}

/// Codes the zig-zag residuals `z` of a `w`-wide tile (row-major) as the payload of heights
/// codec 2.
pub(crate) fn encode(z: &[u32], w: usize) -> Vec<u8> {
    let n = z.len();
    let mut contexts = vec![0u8; n];
    let mut padded = Vec::with_capacity(w + 4);
    for (y, row) in contexts.chunks_exact_mut(w).enumerate() {
        let above = (y > 0).then(|| &z[(y - 1) * w..y * w]);
        row_contexts(above, &mut padded, row);
    }
    let mut histograms = vec![[0u32; TOKENS]; CONTEXTS];
    let mut extra = BitWriter::default();
    let mut tokens = vec![0u8; n];
    for i in 0..n {
        let (t, bits, value) = token(z[i]);
        tokens[i] = t;
        histograms[usize::from(contexts[i])][usize::from(t)] += 1;
        if bits > 0 {
            extra.put(value, bits);
        }
    }

    // Tables: steps per context, written, then normalised as the decoder will.
    let mut table = BitWriter::default();
    let mut cumulative = vec![[(0u16, 0u16); TOKENS]; CONTEXTS];
    for (histogram, cum) in histograms.iter().zip(&mut cumulative) {
        let sum: u64 = histogram.iter().map(|&c| u64::from(c)).sum();
        let used = histogram.iter().rposition(|&c| c > 0).map_or(0, |i| i + 1);
        table.put(used as u32, 8);
        if used == 0 {
            continue;
        }
        let mut steps = [0u8; TOKENS];
        let mut previous = 0i32;
        for (step, &count) in steps.iter_mut().zip(&histogram[..used]) {
            if count > 0 {
                let share = (f64::from(count) * f64::from(TOTAL) / sum as f64).max(1.0);
                *step = ((share.log2() * 2.0).round() as u32 + 1).min(Q_MAX) as u8;
            }
            table.gamma(zigzag_encode(i32::from(*step) - previous) + 1);
            previous = i32::from(*step);
        }
        let freq = normalize(&steps[..used]).expect("a used context has a token");
        let mut start = 0u16;
        for (c, &f) in cum.iter_mut().zip(&freq) {
            *c = (start, f);
            start += f;
        }
    }

    // rANS, backwards, sample x of a row taking state x % 4.
    let mut words: Vec<u16> = Vec::with_capacity(n / 2 + 8);
    let mut states = [RANS_L; STATES];
    for i in (0..n).rev() {
        let (start, freq) = cumulative[usize::from(contexts[i])][usize::from(tokens[i])];
        let (start, freq) = (u32::from(start), u32::from(freq));
        let state = &mut states[(i % w) % STATES];
        let limit = (u64::from(RANS_L >> PROB_BITS) << 16) * u64::from(freq);
        if u64::from(*state) >= limit {
            words.push(*state as u16);
            *state >>= 16;
        }
        *state = ((*state / freq) << PROB_BITS) + (*state % freq) + start;
    }
    for state in states.into_iter().rev() {
        words.push(state as u16);
        words.push((state >> 16) as u16);
    }
    words.reverse();

    let table = table.finish();
    let extra = extra.finish();
    let mut out = Vec::with_capacity(8 + table.len() + extra.len() + words.len() * 2);
    out.extend_from_slice(&(table.len() as u32).to_le_bytes());
    out.extend_from_slice(&(extra.len() as u32).to_le_bytes());
    out.extend_from_slice(&table);
    out.extend_from_slice(&extra);
    for word in words {
        out.extend_from_slice(&word.to_le_bytes());
    }
    out
}

/// What a decoder reuses from tile to tile, per thread.
#[derive(Default)]
struct Scratch {
    /// One table per context, `TOTAL` entries each: token, frequency and offset.
    tables: Vec<u32>,
    /// The rANS words, then zeros, so a word can be read without a bounds branch.
    words: Vec<u32>,
}

thread_local! {
    static SCRATCH: std::cell::RefCell<Scratch> = std::cell::RefCell::new(Scratch::default());
}

/// One step of a state: its token from the context's table, the state advanced and
/// renormalised from `words` (always in bounds: the caller pads them).
#[inline(always)]
fn step(
    state: &mut u32,
    tables: &[u32; TABLES_LEN],
    context: u8,
    words: &[u32],
    next: &mut usize,
) -> u8 {
    let entry = tables[usize::from(context & 15) << PROB_BITS | (*state & SLOT_MASK) as usize];
    let freq = (entry >> 7) & 0x7ff;
    *state = freq * (*state >> PROB_BITS) + (entry >> 18);
    let refill = *state < RANS_L;
    let word = words[*next];
    *state = if refill { *state << 16 | word } else { *state };
    *next += usize::from(refill);
    entry as u8 & 0x7f
}

/// Decodes a codec-2 payload into the zig-zag residuals of a `w x h` tile, handing each row
/// to `row` as soon as it is decoded.
pub(crate) fn decode(
    payload: &[u8],
    w: usize,
    h: usize,
    mut row: impl FnMut(usize, &[u32]),
) -> Result<(), StreamError> {
    let length = |at: usize| -> Result<usize, StreamError> {
        payload
            .get(at..at + 4)
            .map(|b| u32::from_le_bytes(b.try_into().expect("4 bytes")) as usize)
            .ok_or(StreamError::Overrun("section length"))
    };
    let (table_len, extra_len) = (length(0)?, length(4)?);
    let rest = &payload[8..];
    let (table, rest) = rest
        .split_at_checked(table_len)
        .ok_or(StreamError::Overrun("table"))?;
    let (extra, words) = rest
        .split_at_checked(extra_len)
        .ok_or(StreamError::Overrun("raw bits"))?;
    if words.len() % 2 != 0 || words.len() < 4 * STATES {
        return Err(StreamError::BadEnd("the rANS words are not whole"));
    }

    SCRATCH.with_borrow_mut(|scratch| {
        let Scratch {
            tables,
            words: padded_words,
        } = scratch;
        // Filled for the contexts the tile has tables for (bit `c` of `has_table`), and
        // only those are read.
        tables.resize(TABLES_LEN, 0);
        let mut has_table = 0u32;
        let mut reader = BitReader::new(table);
        for context in 0..CONTEXTS {
            let used = reader.get(8) as usize;
            if used == 0 {
                continue;
            }
            has_table |= 1 << context;
            if used > TOKENS {
                return Err(StreamError::Table("more tokens than there are"));
            }
            let mut steps = [0u8; TOKENS];
            let mut previous = 0i32;
            for step in &mut steps[..used] {
                let q = previous + zigzag_decode(reader.gamma()? - 1);
                if !(0..=Q_MAX as i32).contains(&q) {
                    return Err(StreamError::Table("a frequency step out of range"));
                }
                *step = q as u8;
                previous = q;
            }
            let freq = normalize(&steps[..used]).ok_or(StreamError::Table("an empty table"))?;
            let slots = &mut tables[context * TOTAL as usize..(context + 1) * TOTAL as usize];
            let mut start = 0usize;
            for (t, &f) in freq.iter().enumerate() {
                let entry = t as u32 | u32::from(f) << 7;
                for (bias, slot) in slots[start..start + usize::from(f)].iter_mut().enumerate() {
                    *slot = entry | (bias as u32) << 18;
                }
                start += usize::from(f);
            }
        }
        if reader.overrun() || !reader.used_exactly() {
            return Err(StreamError::Table("its length is not what it holds"));
        }

        let word_count = words.len() / 2;
        padded_words.clear();
        padded_words.extend(
            words
                .chunks_exact(2)
                .map(|b| u32::from(u16::from_le_bytes([b[0], b[1]]))),
        );
        // Every step reads at most one word, so a row reads at most `w`: a state that reads
        // past the end reads zeros, and is caught at the end of its row.
        padded_words.resize(word_count + w + STATES, 0);
        let mut raw = BitReader::new(extra);

        let words = &padded_words[..];
        let mut states = [0u32; STATES];
        for (i, state) in states.iter_mut().enumerate() {
            *state = words[2 * i] << 16 | words[2 * i + 1];
        }
        let [mut s0, mut s1, mut s2, mut s3] = states;
        let mut next = 2 * STATES;
        let tables: &[u32; TABLES_LEN] = tables[..].try_into().expect("sized above");
        let mut contexts = vec![0u8; w];
        let mut tokens = vec![0u8; w];
        let mut padded = Vec::with_capacity(w + 4);
        let mut above = vec![0u32; w];
        let mut current = vec![0u32; w];
        for y in 0..h {
            row_contexts((y > 0).then_some(&above[..]), &mut padded, &mut contexts);
            let used = contexts.iter().fold(0u32, |m, &c| m | 1 << (c & 15));
            if used & !has_table != 0 {
                return Err(StreamError::MissingTable(
                    (used & !has_table).trailing_zeros() as u8,
                ));
            }
            let mut token_chunks = tokens.chunks_exact_mut(STATES);
            let mut context_chunks = contexts.chunks_exact(STATES);
            for (t, c) in (&mut token_chunks).zip(&mut context_chunks) {
                t[0] = step(&mut s0, tables, c[0], words, &mut next);
                t[1] = step(&mut s1, tables, c[1], words, &mut next);
                t[2] = step(&mut s2, tables, c[2], words, &mut next);
                t[3] = step(&mut s3, tables, c[3], words, &mut next);
            }
            let (t, c) = (token_chunks.into_remainder(), context_chunks.remainder());
            let mut rest = [&mut s0, &mut s1, &mut s2];
            for ((t, &c), state) in t.iter_mut().zip(c).zip(&mut rest) {
                *t = step(state, tables, c, words, &mut next);
            }
            for (z, &t) in current.iter_mut().zip(&tokens) {
                let t = usize::from(t & 0x7f);
                *z = TOKEN_BASE[t] | raw.get(u32::from(TOKEN_BITS[t]));
            }
            if next > word_count {
                return Err(StreamError::Overrun("rANS"));
            }
            row(y, &current);
            std::mem::swap(&mut above, &mut current);
        }
        if next > word_count {
            return Err(StreamError::Overrun("rANS"));
        }
        if raw.overrun() {
            return Err(StreamError::Overrun("raw bits"));
        }
        if next != word_count {
            return Err(StreamError::BadEnd("rANS words left over"));
        }
        if !raw.used_exactly() {
            return Err(StreamError::BadEnd("raw bits left over"));
        }
        if [s0, s1, s2, s3] != [RANS_L; STATES] {
            return Err(StreamError::BadEnd(
                "the rANS states do not end where they began",
            ));
        }
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tokens_cover_every_u32_and_invert() {
        for z in (0..5000u32).chain([u32::MAX, u32::MAX - 1, 1 << 31, (1 << 31) - 1, 65535, 65536])
        {
            let (t, bits, value) = token(z);
            assert_eq!(u32::from(TOKEN_BITS[usize::from(t)]), bits, "{z}");
            assert_eq!(TOKEN_BASE[usize::from(t)] | value, z, "{z}");
        }
    }

    /// A stream whose table for a context it uses is taken out is refused, naming the
    /// context (row 0's, which every tile uses).
    #[test]
    fn a_context_used_without_a_table_is_refused_by_name() {
        let w = 9;
        let z: Vec<u32> = (0..w * 7).map(|i| (i * 7 % 23) as u32).collect();
        let payload = encode(&z, w);
        let length = |at: usize| u32::from_le_bytes(payload[at..at + 4].try_into().expect("4"));
        let table_len = length(0) as usize;
        let table = &payload[8..8 + table_len];
        // The same tables, row 0's written as absent.
        let mut reader = BitReader::new(table);
        let mut writer = BitWriter::default();
        for context in 0..CONTEXTS {
            let used = reader.get(8);
            let steps: Vec<u32> = (0..used).map(|_| reader.gamma().expect("a step")).collect();
            if context == usize::from(FIRST_ROW) {
                assert!(used > 0, "row 0 has a table");
                writer.put(0, 8);
                continue;
            }
            writer.put(used, 8);
            for step in steps {
                writer.gamma(step);
            }
        }
        let without = writer.finish();
        let mut stream = Vec::new();
        stream.extend_from_slice(&(without.len() as u32).to_le_bytes());
        stream.extend_from_slice(&payload[4..8]);
        stream.extend_from_slice(&without);
        stream.extend_from_slice(&payload[8 + table_len..]);
        assert_eq!(decode(&payload, w, 7, |_, _| {}), Ok(()));
        assert_eq!(
            decode(&stream, w, 7, |_, _| {}),
            Err(StreamError::MissingTable(FIRST_ROW))
        );
    }

    #[test]
    fn normalized_tables_always_sum_to_the_total() {
        let mut rng = 0x1234_5678_9abc_def0u64;
        for _ in 0..2000 {
            let mut steps = [0u8; TOKENS];
            let used = (rng % TOKENS as u64) as usize + 1;
            for step in &mut steps[..used] {
                rng ^= rng << 13;
                rng ^= rng >> 7;
                rng ^= rng << 17;
                *step = (rng % 32) as u8;
            }
            steps[used - 1] = steps[used - 1].max(1);
            let freq = normalize(&steps[..used]).expect("a step is set");
            assert_eq!(freq.iter().map(|&f| u32::from(f)).sum::<u32>(), TOTAL);
            for (f, q) in freq.iter().zip(&steps) {
                assert_eq!(*f > 0, *q > 0);
            }
        }
        assert_eq!(normalize(&[0, 0, 0]), None);
        let all = [31u8; TOKENS];
        assert!(normalize(&all).is_some());
    }
}
