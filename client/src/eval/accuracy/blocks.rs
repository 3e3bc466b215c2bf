//! What regular grids chosen per block of a tile need against the oracle
//! (`bench accuracy --block-grids`): how near the oracle a regular-grid method (GeoMipMaps,
//! strip masks) can come by choosing its level per block rather than per tile, and what one
//! strip mask a tile needs under the tightest sound bound.

use super::{AccuracyReport, at_sample, for_full_resolution_tiles_in_view};
use crate::eval::oracle::{BlockGrids, block_grid_triangles, one_mask_triangles};
use crate::render::Camera;

/// The blocks [`block_grid_counts`] cuts tiles into, cells.
const BLOCKS: [u32; 6] = [128, 64, 32, 16, 8, 4];

/// One camera's counts: per block size, the regular grids chosen per block; and one strip
/// mask a tile with each sample's error projected at the sample ([`one_mask_triangles`]).
#[derive(Debug, Clone, Default)]
pub(super) struct BlockCounts {
    pub blocks: Vec<(u32, BlockGrids)>,
    pub one_mask: u64,
}

/// Per block size of [`BLOCKS`] smaller than a tile, what regular grids chosen per block need
/// for `camera`'s frame ([`block_grid_triangles`]), over the tiles the oracle
/// counts ([`oracle_triangles`]), each block's pixels per metre at its own box; and what one
/// mask a tile needs, each sample's pixels per metre at the sample, as the oracle's.
pub(super) fn block_grid_counts(
    scene: &crate::scene::Scene,
    camera: &Camera,
    viewport: [u32; 2],
    threshold_px: f64,
) -> BlockCounts {
    let projection = crate::lod::plan::error_projection(camera, viewport);
    let mut totals: Vec<(u32, BlockGrids)> = Vec::new();
    let mut one_mask = 0;
    for_full_resolution_tiles_in_view(scene, camera, viewport, |[x0, y0], spacing, samples, n| {
        let ppm = |c: u32, r: u32| {
            at_sample(
                &projection,
                [x0, y0],
                spacing,
                samples,
                n,
                (c, r),
                threshold_px,
            )
        };
        one_mask += one_mask_triangles(samples, n, ppm, threshold_px);
        for block in BLOCKS.into_iter().filter(|&b| b < n) {
            let ppm = |bc: u32, br: u32| {
                let (c0, r0) = (bc * block, br * block);
                let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
                for r in r0..=r0 + block {
                    for &h in &samples[(r * n + c0) as usize..=(r * n + c0 + block) as usize] {
                        lo = lo.min(h);
                        hi = hi.max(h);
                    }
                }
                let at = |c: u32, r: u32, h: f32| {
                    [
                        x0 + f64::from(c) * spacing[0],
                        y0 + f64::from(r) * spacing[1],
                        f64::from(h),
                    ]
                };
                projection.pixels_per_metre(
                    at(c0, r0, lo),
                    at(c0 + block, r0 + block, hi),
                    threshold_px,
                )
            };
            let counts = block_grid_triangles(samples, n, block, ppm, threshold_px);
            match totals.iter_mut().find(|(b, _)| *b == block) {
                Some((_, t)) => {
                    t.geomipmap += counts.geomipmap;
                    t.strip += counts.strip;
                }
                None => totals.push((block, counts)),
            }
        }
    });
    BlockCounts {
        blocks: totals,
        one_mask,
    }
}

/// The table of OUT/block-grids.md: per block size, the regular grids' triangles summed over
/// the cameras against the oracle's at the threshold.
pub(super) fn block_grids_markdown(report: &AccuracyReport, per_camera: &[BlockCounts]) -> String {
    let oracle: u64 = report
        .oracle
        .iter()
        .filter_map(|c| {
            c.iter()
                .find(|(t, _)| *t == report.threshold_px)
                .map(|(_, n)| *n)
        })
        .sum();
    let ratio = |n: u64| n as f64 / oracle.max(1) as f64;
    let mut out = format!(
        "Regular grids chosen per block against the oracle ({}, {}x{}, {} cameras, {} px; the \
         oracle: {oracle} triangles summed over the cameras, as are the counts below). Each block at the coarsest GeoMipMap \
         level (power-of-two step) or strip-mask step within the threshold at its own nearest \
         point; seams not counted.\n\n\
         | block (cells) | GeoMipMap levels | times the oracle | strip masks | times the oracle |\n\
         |---:|---:|---:|---:|---:|\n",
        report.dataset, report.size.0, report.size.1, report.cameras, report.threshold_px
    );
    for block in BLOCKS {
        let (mut geomipmap, mut strip, mut seen) = (0, 0, false);
        for camera in per_camera {
            if let Some((_, c)) = camera.blocks.iter().find(|(b, _)| *b == block) {
                geomipmap += c.geomipmap;
                strip += c.strip;
                seen = true;
            }
        }
        if seen {
            out += &format!(
                "| {block} | {geomipmap} | {:.2} | {strip} | {:.2} |\n",
                ratio(geomipmap),
                ratio(strip)
            );
        }
    }
    let one_mask: u64 = per_camera.iter().map(|c| c.one_mask).sum();
    out += &format!(
        "\nOne strip mask a tile, as the strip-mask method draws, with each sample's error \
         projected at the sample itself (the tightest sound bound, so the least any bound can \
         give one mask a tile): {one_mask} triangles, {:.2} times the oracle.\n",
        ratio(one_mask)
    );
    out
}
