//! Filling no-data voids from their valid neighbours, so no void ever reaches a tile as a
//! spike (SRTM voids are -32768 m).
//!
//! Voids are filled in waves from their rims inwards: each wave gives every void sample
//! that touches a known one (valid or filled by an earlier wave) the mean of its known
//! 8-neighbours. The result is a smooth membrane that meets the surrounding terrain on
//! every side, which is the usual behaviour of GIS fill tools for small voids; large voids
//! become plausible but invented terrain, which is why they are reported.
//!
//! **Filling is global.** A void sample's value depends on the whole void it belongs to
//! (the waves reach it from every rim), and a void may span any number of bands of tile
//! rows (a river channel, a swath of radar shadow), so no window of bands fills it as the
//! whole raster does, and the output must not depend on how the heights were read. A
//! raster with voids is therefore read whole and filled here before the builder takes its
//! rows from memory ([`crate::build`]); a void-free raster, which the scan of a streamed
//! file tells apart, is never held whole.

/// What filling did, for the build's warnings.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FillReport {
    pub samples: usize,
    /// Connected (8-neighbour) void regions.
    pub regions: usize,
    pub largest_region: usize,
}

/// Fills every `true` of `voids` in `codes` (row-major `width x height`).
/// Returns `None` when there was nothing to fill. At least one sample must be valid.
pub fn fill(codes: &mut [i32], voids: &[bool], width: usize, height: usize) -> Option<FillReport> {
    if voids.is_empty() || !voids.iter().any(|&v| v) {
        return None;
    }
    let report = FillReport {
        samples: voids.iter().filter(|&&v| v).count(),
        ..region_sizes(voids, width, height)
    };
    let mut known: Vec<bool> = voids.iter().map(|&v| !v).collect();
    let mut wave: Vec<usize> = (0..codes.len())
        .filter(|&i| voids[i] && touches_known(i, &known, width, height))
        .collect();
    let mut next = Vec::new();
    let mut fills = Vec::new();
    while !wave.is_empty() {
        fills.clear();
        for &i in &wave {
            let (sum, count) = neighbours(i, width, height)
                .filter(|&j| known[j])
                .fold((0i64, 0i64), |(s, c), j| (s + i64::from(codes[j]), c + 1));
            fills.push((i, (sum as f64 / count as f64).round() as i32));
        }
        for &(i, value) in &fills {
            codes[i] = value;
            known[i] = true;
        }
        next.clear();
        for &(i, _) in &fills {
            for j in neighbours(i, width, height) {
                if !known[j] {
                    next.push(j);
                }
            }
        }
        next.sort_unstable();
        next.dedup();
        std::mem::swap(&mut wave, &mut next);
    }
    Some(report)
}

fn neighbours(i: usize, width: usize, height: usize) -> impl Iterator<Item = usize> {
    let (x, y) = ((i % width) as isize, (i / width) as isize);
    (-1isize..=1)
        .flat_map(move |dy| (-1isize..=1).map(move |dx| (x + dx, y + dy)))
        .filter_map(move |(nx, ny)| {
            let inside = nx >= 0
                && ny >= 0
                && (nx as usize) < width
                && (ny as usize) < height
                && (nx, ny) != (x, y);
            inside.then(|| ny as usize * width + nx as usize)
        })
}

fn touches_known(i: usize, known: &[bool], width: usize, height: usize) -> bool {
    neighbours(i, width, height).any(|j| known[j])
}

fn region_sizes(voids: &[bool], width: usize, height: usize) -> FillReport {
    let mut seen = vec![false; voids.len()];
    let (mut regions, mut largest) = (0, 0);
    let mut stack = Vec::new();
    for start in 0..voids.len() {
        if !voids[start] || seen[start] {
            continue;
        }
        regions += 1;
        let mut size = 0;
        seen[start] = true;
        stack.push(start);
        while let Some(i) = stack.pop() {
            size += 1;
            for j in neighbours(i, width, height) {
                if voids[j] && !seen[j] {
                    seen[j] = true;
                    stack.push(j);
                }
            }
        }
        largest = largest.max(size);
    }
    FillReport {
        samples: 0,
        regions,
        largest_region: largest,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn check(
        width: usize,
        codes: &[i32],
        voids: &[bool],
        expected: &[i32],
        report: Option<FillReport>,
    ) {
        let mut filled = codes.to_vec();
        let got = fill(&mut filled, voids, width, codes.len() / width);
        assert_eq!(filled, expected);
        assert_eq!(got, report);
    }

    #[test]
    fn a_single_void_takes_the_mean_of_its_neighbours() {
        let v = [false, false, false, false, true, false, false, false, false];
        check(
            3,
            &[1, 1, 1, 1, -32768, 1, 1, 1, 9],
            &v,
            &[1, 1, 1, 1, 2, 1, 1, 1, 9],
            Some(FillReport {
                samples: 1,
                regions: 1,
                largest_region: 1,
            }),
        );
    }

    #[test]
    fn a_void_on_a_slope_is_filled_inside_the_slopes_range() {
        // 5x1 ramp with the three middle samples missing.
        let v = [false, true, true, true, false];
        let mut codes = [0, -32768, -32768, -32768, 40];
        fill(&mut codes, &v, 5, 1);
        assert!(codes.iter().all(|&c| (0..=40).contains(&c)), "{codes:?}");
        assert!(codes[1] <= codes[2] && codes[2] <= codes[3]);
    }

    #[test]
    fn separate_voids_are_counted_as_regions() {
        let v = [true, false, false, false, true, true];
        check(
            6,
            &[0, 5, 5, 5, 0, 0],
            &v,
            &[5, 5, 5, 5, 5, 5],
            Some(FillReport {
                samples: 3,
                regions: 2,
                largest_region: 2,
            }),
        );
    }

    #[test]
    fn nothing_to_fill_reports_nothing() {
        check(2, &[1, 2], &[], &[1, 2], None);
        check(2, &[1, 2], &[false, false], &[1, 2], None);
    }
}
