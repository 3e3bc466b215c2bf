//! What a tile's GPU buffers hold, computed on the CPU once per tile: its samples with
//! normals, and the skirt strips of each mask level.

use terrain_shaders::{Sample, pack_normal};
use terrain_shared::{Heights, mask};

/// The samples of a tile in its storage buffer: height in metres and a unit normal in
/// render space (x east, y up, z south), computed once at the finest level by central
/// differences (one-sided on the tile's edges), whatever mask draws the tile.
pub fn tile_samples(heights: &Heights, spacing_m: [f64; 2]) -> Vec<Sample> {
    let (w, h) = (heights.width as usize, heights.height as usize);
    let metres = heights.to_metres_f32();
    let at = |x: usize, y: usize| f64::from(metres[y * w + x]);
    let mut out = Vec::with_capacity(w * h);
    for y in 0..h {
        let (y0, y1) = (y.saturating_sub(1), (y + 1).min(h - 1));
        for x in 0..w {
            let (x0, x1) = (x.saturating_sub(1), (x + 1).min(w - 1));
            let dx = (at(x1, y) - at(x0, y)) / (((x1 - x0).max(1)) as f64 * spacing_m[0]);
            let dy = (at(x, y1) - at(x, y0)) / (((y1 - y0).max(1)) as f64 * spacing_m[1]);
            // Surface height(east, south): the normal is (-dh/deast, 1, -dh/dsouth) in render space.
            let n = glam::DVec3::new(-dx, 1.0, -dy).normalize();
            out.push(Sample {
                height: metres[y * w + x],
                normal: pack_normal([n.x as f32, n.y as f32, n.z as f32]),
            });
        }
    }
    out
}

/// The skirts of mask `level` as one triangle strip: along each edge of the tile, a
/// vertical band from each kept border sample (index `i`) down to its foot (index
/// `tile_size^2 + i`, which the shader places at the skirt's bottom). Edges are joined by
/// repeated indices, like the mask strips. The strip-mask paper's "filleting" (section 5.4).
pub fn skirt_strip(tile_size: u32, level: u32) -> Vec<u32> {
    let kept = mask::kept_indices(tile_size, level);
    let n = tile_size;
    let last = n - 1;
    let feet = terrain_shaders::skirt_base(n);
    // Each edge walks its kept samples in order round the tile (north west to east, east
    // north to south, south east to west, west south to north); `kept` is not symmetric,
    // so the last two walk it backwards.
    let forward: Vec<u32> = kept.clone();
    let backward: Vec<u32> = kept.iter().rev().copied().collect();
    let edges: [(Vec<u32>, u32, u32); 4] = [
        (forward.clone(), 0, 1),         // north: k
        (forward, last, n),              // east: k * n + last
        (backward.clone(), last * n, 1), // south: last * n + k
        (backward, 0, n),                // west: k * n
    ];
    let mut strip: Vec<u32> = Vec::with_capacity(4 * (2 * kept.len() + 2));
    for (ks, first, step) in &edges {
        let at = |k: u32| first + k * step;
        if let Some(&previous) = strip.last() {
            strip.push(previous);
            strip.push(at(ks[0]));
        }
        for &k in ks {
            let i = at(k);
            strip.push(i);
            strip.push(feet + i);
        }
    }
    strip
}

/// Triangles a skirt strip draws (joins not counted): two per kept border cell, four edges.
pub fn skirt_triangles(tile_size: u32, level: u32) -> u32 {
    let kept = mask::kept_indices(tile_size, level).len() as u32;
    8 * (kept - 1)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn plane(n: u32, slope_east: f64, slope_south: f64, spacing: f64) -> Heights {
        let codes = (0..n * n)
            .map(|i| {
                let (x, y) = (f64::from(i % n), f64::from(i / n));
                ((x * slope_east + y * slope_south) * spacing * 100.0).round() as i32
            })
            .collect();
        Heights {
            width: n as u16,
            height: n as u16,
            quantum_m: 0.01,
            offset_m: 0.0,
            codes,
        }
    }

    fn unpack(n: u32) -> [f64; 3] {
        let c = |i: u32| f64::from(((n >> (8 * i)) & 0xff) as u8 as i8) / 127.0;
        [c(0), c(1), c(2)]
    }

    #[test]
    fn a_flat_tile_has_upward_normals_and_a_slope_tilts_them_downhill() {
        for s in tile_samples(&plane(5, 0.0, 0.0, 10.0), [10.0, 10.0]) {
            assert_eq!(unpack(s.normal), [0.0, 1.0, 0.0]);
        }
        // Rising 1 m per metre eastwards: the normal leans west, at 45 degrees, everywhere
        // (edges included: one-sided differences see the same slope).
        for s in tile_samples(&plane(5, 1.0, 0.0, 10.0), [10.0, 10.0]) {
            let [x, y, z] = unpack(s.normal);
            let h = std::f64::consts::FRAC_1_SQRT_2;
            assert!((x + h).abs() < 0.01 && (y - h).abs() < 0.01 && z.abs() < 0.01);
        }
        // Rising southwards: leans north (negative z in render space).
        let s = tile_samples(&plane(5, 0.0, 0.5, 10.0), [10.0, 10.0])[12];
        assert!(unpack(s.normal)[2] < -0.3);
    }

    #[test]
    fn skirts_hang_from_every_kept_border_sample_and_only_those() {
        for (n, level) in [(5, 0), (9, 2), (129, 5), (129, 127)] {
            let strip = skirt_strip(n, level);
            let kept = mask::kept_indices(n, level);
            let mut border: Vec<u32> = strip.iter().copied().filter(|&i| i < n * n).collect();
            border.sort_unstable();
            border.dedup();
            let last = n - 1;
            let mut expected: Vec<u32> = Vec::new();
            for &a in &kept {
                for &b in &kept {
                    if a == 0 || a == last || b == 0 || b == last {
                        expected.push(b * n + a);
                    }
                }
            }
            expected.sort_unstable();
            expected.dedup();
            assert_eq!(border, expected, "tile {n} level {level}");
            // Every foot sits under a border sample.
            assert!(
                strip
                    .iter()
                    .all(|&i| i < n * n || expected.contains(&(i - n * n)))
            );
            // Drawn (non-degenerate) triangles: each has two distinct samples and a foot, or
            // two feet and a sample.
            let drawn = strip
                .windows(3)
                .filter(|t| t[0] != t[1] && t[1] != t[2] && t[0] != t[2])
                .count() as u32;
            assert_eq!(drawn, skirt_triangles(n, level), "tile {n} level {level}");
        }
    }
}
