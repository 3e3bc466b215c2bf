//! zstd frames read in Rust (ruzstd): how the browser build, which has no zstd C library,
//! reads `planar-zstd/1` heights and quadtree patches. The native build reads them with
//! zstd's own decoder; the tests here check that both give the same bytes, and refuse the
//! same hostile frames.
//!
//! A frame's window is memory the decoder reserves before it decodes a byte, so it is read
//! from the frame's header first (RFC 8878, 3.1.1.1) and refused past what the output
//! needs, as natively: the output's size rounded up to a power of two, and at least 8 MiB
//! (the window of zstd's levels up to 19, which plain streaming compressors write).

use std::io::Read as _;

/// What a frame could not give.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum FrameError {
    /// The frame holds more bytes than its output has room for.
    PastEnd,
    Zstd(String),
}

impl std::fmt::Display for FrameError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            FrameError::PastEnd => write!(f, "the frame holds more than it may"),
            FrameError::Zstd(why) => write!(f, "{why}"),
        }
    }
}

/// The largest window a frame whose output is `out_len` bytes may ask for.
fn window_limit(out_len: usize) -> u64 {
    (out_len.max(1).next_power_of_two() as u64).max(1 << 23)
}

/// The window the zstd frame at the front of `input` asks for, from its header.
fn window_size(input: &[u8]) -> Result<u64, FrameError> {
    let short = || FrameError::Zstd("the frame header is cut short".into());
    let magic = input.get(..4).ok_or_else(short)?;
    if magic != [0x28, 0xb5, 0x2f, 0xfd] {
        return Err(FrameError::Zstd(
            "not a zstd frame (bad magic number)".into(),
        ));
    }
    let descriptor = *input.get(4).ok_or_else(short)?;
    let single_segment = descriptor & 0x20 != 0;
    if !single_segment {
        let byte = *input.get(5).ok_or_else(short)?;
        let base = 1u64 << (10 + u32::from(byte >> 3));
        return Ok(base + base / 8 * u64::from(byte & 7));
    }
    // A single segment's window is its content size, which follows the dictionary id.
    let dictionary = [0, 1, 2, 4][usize::from(descriptor & 3)];
    let size_bytes = [1, 2, 4, 8][usize::from(descriptor >> 6)];
    let at = 5 + dictionary;
    let field = input.get(at..at + size_bytes).ok_or_else(short)?;
    let mut le = [0u8; 8];
    le[..size_bytes].copy_from_slice(field);
    let value = u64::from_le_bytes(le);
    Ok(if size_bytes == 2 { value + 256 } else { value })
}

/// Decodes the zstd frame at the front of `input` into `out`: the bytes written and the
/// bytes of `input` the frame took. [`FrameError::PastEnd`] when it holds more than `out`.
pub(crate) fn decode_frame_into(
    input: &[u8],
    out: &mut [u8],
) -> Result<(usize, usize), FrameError> {
    let window = window_size(input)?;
    if window > window_limit(out.len()) {
        return Err(FrameError::Zstd(format!(
            "the frame asks for a window of {window} bytes, more than its {} bytes of output need",
            out.len()
        )));
    }
    let mut source = input;
    let zstd = |e: &dyn std::fmt::Display| FrameError::Zstd(e.to_string());
    let mut decoder = ruzstd::decoding::StreamingDecoder::new(&mut source).map_err(|e| zstd(&e))?;
    let mut written = 0;
    while written < out.len() {
        match decoder.read(&mut out[written..]).map_err(|e| zstd(&e))? {
            0 => break,
            read => written += read,
        }
    }
    if written == out.len() {
        let mut beyond = [0u8; 1];
        if decoder.read(&mut beyond).map_err(|e| zstd(&e))? > 0 {
            return Err(FrameError::PastEnd);
        }
    }
    drop(decoder);
    Ok((written, input.len() - source.len()))
}

/// Every zstd frame of `input`, back to back, as one output of at most `max` bytes (what
/// zstd's `bulk::decompress(input, max)` gives natively).
pub(crate) fn decode_frames(input: &[u8], max: usize) -> Result<Vec<u8>, FrameError> {
    let mut out = Vec::new();
    let mut rest = input;
    while !rest.is_empty() {
        let start = out.len();
        // Room for what is left of `max`, grown as frames fill it.
        out.resize(max, 0);
        let (written, taken) = decode_frame_into(rest, &mut out[start..])?;
        out.truncate(start + written);
        rest = &rest[taken..];
    }
    Ok(out)
}

#[cfg(all(test, not(target_arch = "wasm32")))]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn a_frame_decodes_as_zstd_decodes_it_and_says_how_much_input_it_took() {
        let data: Vec<u8> = (0..20_000u32).map(|i| (i * 7 % 251) as u8).collect();
        for level in [1, 3, 19] {
            let frame = zstd::bulk::compress(&data, level).expect("compresses");
            let mut input = frame.clone();
            input.extend_from_slice(b"tail");
            let mut out = vec![0u8; data.len()];
            let (written, taken) = decode_frame_into(&input, &mut out).expect("decodes");
            assert_eq!((written, taken), (data.len(), frame.len()), "level {level}");
            assert_eq!(out, data);
            // One byte short of room: refused.
            let mut small = vec![0u8; data.len() - 1];
            assert_eq!(
                decode_frame_into(&frame, &mut small),
                Err(FrameError::PastEnd)
            );
        }
    }

    #[test]
    fn frames_back_to_back_decode_as_one_output_within_the_limit() {
        let (a, b) = (vec![1u8; 3000], vec![2u8; 5000]);
        let mut input = zstd::bulk::compress(&a, 3).expect("compresses");
        input.extend(zstd::stream::encode_all(&b[..], 3).expect("compresses"));
        let both = decode_frames(&input, 8000).expect("decodes");
        assert_eq!(
            both,
            zstd::bulk::decompress(&input, 8000).expect("zstd decodes")
        );
        assert_eq!(both.len(), 8000);
        assert!(decode_frames(&input, 7999).is_err(), "past the limit");
    }

    #[test]
    fn a_frame_asking_for_a_window_past_its_output_is_refused_before_decoding() {
        // A streamed frame (no content size) with a 128 MiB window, over a tiny output.
        let mut frame = vec![0x28, 0xb5, 0x2f, 0xfd, 0x00, (27 - 10) << 3];
        frame.extend_from_slice(&[0x01, 0x00, 0x00]); // a last, empty raw block
        let mut out = [0u8; 16];
        let refused = decode_frame_into(&frame, &mut out);
        assert!(
            matches!(&refused, Err(FrameError::Zstd(why)) if why.contains("window of 134217728 bytes")),
            "{refused:?}"
        );
        // The same frame with an 8 MiB window is read (it is empty).
        frame[5] = (23 - 10) << 3;
        assert_eq!(decode_frame_into(&frame, &mut out), Ok((0, 9)));
    }

    #[test]
    fn bad_input_is_an_error_never_a_panic() {
        let mut out = [0u8; 64];
        for input in [
            &b""[..],
            b"\x28\xb5\x2f",
            b"not a frame at all",
            b"\x28\xb5\x2f\xfd\x20",
        ] {
            assert!(decode_frame_into(input, &mut out).is_err(), "{input:?}");
        }
    }

    proptest! {
        /// Any bytes, and any corruption of a good frame: an error or bytes, never a panic,
        /// never more than the output has room for.
        #[test]
        fn arbitrary_and_corrupted_frames_never_panic(
            data in proptest::collection::vec(any::<u8>(), 0..2000),
            flip in any::<(usize, u8)>(),
            cut in any::<usize>(),
        ) {
            let mut frame = zstd::bulk::compress(&data, 3).expect("compresses");
            let at = flip.0 % frame.len();
            frame[at] ^= flip.1;
            frame.truncate(cut % (frame.len() + 1));
            let mut out = vec![0u8; 2000];
            if let Ok((written, taken)) = decode_frame_into(&frame, &mut out) {
                prop_assert!(written <= 2000 && taken <= frame.len());
            }
            let _ = decode_frames(&data, 2000);
        }
    }
}
