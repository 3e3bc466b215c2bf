//! What a tile's sample buffer holds, computed on the CPU once per tile: its samples with
//! normals.

use terrain_shaders::{Sample, pack_normal};
use terrain_shared::Heights;

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
}
