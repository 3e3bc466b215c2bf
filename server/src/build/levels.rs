//! The pyramid of levels, built a band of tile rows at a time while level 0 streams in, so
//! that a build's memory does not grow with the raster's height, and grows with its width
//! only by about two bands of level 0 (`benches/build_memory.rs`).
//!
//! Level 0 is the raster; level `k + 1` keeps every other sample of level `k`
//! ([`tiles::decimate`]) and is cut into the same `(2^n + 1)^2` tiles, until a level fits
//! in one tile ([`terrain_shared::manifest::level_rasters`]). Keeping samples rather than
//! filtering them keeps a coarse tile's vertices on the full-resolution surface, makes a
//! level seam a T-junction like a mask seam, and makes bounds and errors compose exactly
//! (ARCHITECTURE.md, "Levels").
//!
//! Rows of level 0 arrive one at a time ([`Pyramid::push_row`]). When level 0 holds its
//! next tile row's rows it makes that row, and with it every coarser row it completes
//! (level `k + 1`'s next row, when level `k`'s is odd or its last): a *climb*. Each level
//! holds only what its next tile row needs:
//!
//! - rows: level 0 stores its band (`tile_size` rows, consecutive tile rows sharing one)
//!   and [`texture::GENERATED_HALO_ROWS`] more on either side for computed textures. A
//!   coarser level's row `y` is every other sample of the finer level's row `2y`, so while
//!   the finer level holds that row the coarser one sees it through it (a strided
//!   [`tiles::Row`]); it stores only its band's top half, which it still needs when the
//!   finer band has moved on (`store_for`, top down after each climb);
//! - per tile of its next row, what its children handed up ([`Parent`]): their bounds,
//!   their distance from full resolution, their half-resolution errors and their textures
//!   halved and compressed ([`texture::ChildTexture`]).
//!
//! A climb's tiles are made on rayon's threads, a few at a time, and written on the
//! calling thread in row-major order per level ([`DbWriter::add_level_heights`]: each level
//! to files of its own, put in manifest order at the end). A parent is queued, with its
//! children's carries, as soon as its last child is written, ahead of the finer row's
//! remaining tiles: only the north children's carries wait, for the south row.
//!
//! A tile's decimation error needs the finer level's samples under it
//! ([`tiles::decimation_error`]), but no coarse cell straddles two children, so it is the
//! largest of the children's half-resolution errors, which each child has from its own mask
//! errors. Where a parent on the grid's edge lacks children, the padding that stands in
//! for them (the edge repeated) is measured by the tile beside it, from its own rows:
//! usually equal to that tile's edge cells, it can exceed them by an f32 step (tested).

use super::texture::{self, ChildTexture, Edges, HeightField, Registration};
use super::tiles::{self, Band, Grid, TileStats};
use super::{BuildError, ProgressFn};
use crate::db::{DbWriter, WriteError};
use image::RgbImage;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use terrain_shared::manifest::{self, GridSize, ImageFormat, Level, RasterSize};
use terrain_shared::{Blob, TileBlob, TileId, TileRecord};

/// Where a pyramid's tiles go: a database being written, or a region job's files
/// ([`super::jobs`]). Blobs arrive in row-major order per level.
pub(super) trait TileSink: std::fmt::Debug {
    fn add_level_heights(&mut self, level: u32, bytes: &[u8]) -> Result<Blob, WriteError>;
    fn add_level_texture(&mut self, level: u32, bytes: &[u8]) -> Result<Blob, WriteError>;
}

impl TileSink for DbWriter {
    fn add_level_heights(&mut self, level: u32, bytes: &[u8]) -> Result<Blob, WriteError> {
        DbWriter::add_level_heights(self, level, bytes)
    }
    fn add_level_texture(&mut self, level: u32, bytes: &[u8]) -> Result<Blob, WriteError> {
        DbWriter::add_level_texture(self, level, bytes)
    }
}

/// What every tile of a build shares.
#[derive(Debug)]
pub(super) struct TileContext<'a> {
    pub tile_size: u32,
    pub quantum_m: f64,
    pub offset_m: f64,
    /// Smallest and largest code of level 0 (and so of every level).
    pub code_range: (i32, i32),
    pub heights_coder: terrain_shared::heights::Coder,
    pub texture_format: ImageFormat,
    pub jpeg_quality: u8,
    /// Finest texture side, texels.
    pub texture_size: u32,
    pub level_zero_texture: LevelZeroTexture<'a>,
}

/// Where level 0's textures come from (coarser levels' are filtered from their children's).
#[derive(Debug)]
pub(super) enum LevelZeroTexture<'a> {
    /// Resampled from an image held whole, covering a raster of `raster` samples.
    Image {
        image: &'a RgbImage,
        registration: Registration,
        raster: (u32, u32),
    },
    /// Computed from the heights, tinted over the dataset's range.
    Generated {
        spacing_m: [f64; 2],
        min_m: f64,
        max_m: f64,
    },
    /// None: the pyramid starts above level 0 ([`Pyramid::above`]), and every tile's
    /// texture is filtered from its children's.
    FromChildren,
}

/// What a finished pyramid made.
#[derive(Debug)]
pub(super) struct Built {
    pub levels: Vec<Level>,
    pub heights_bytes: u64,
    pub texture_bytes: u64,
    /// Encoded bytes of each texture level (coarsest first), over every tile.
    pub texture_level_bytes: Vec<u64>,
    /// Samples stored in tiles, padding included.
    pub tile_samples: u64,
}

/// The levels being built. See the module docs.
pub(super) struct Pyramid<'a> {
    tiles: TileMaker<'a>,
    /// The levels this pyramid makes: all of them ([`Pyramid::new`]), those up to a region
    /// job's split level ([`Pyramid::region`]), or those above it ([`Pyramid::above`]).
    levels: Vec<LevelState>,
    /// A region job's hand-over to the merge, gathered as its top level's rows are made.
    handover: Option<Handover>,
    /// Above a split level: the children's carries of each tile row of the first level.
    children: Option<ChildrenFn<'a>>,
    /// Per level (none at level 0), per tile of its next tile row, what its children have
    /// handed up so far.
    pending: Vec<Vec<Parent>>,
    /// Per level, the records of the tiles written so far.
    records: Vec<Vec<Written>>,
    heights_bytes: u64,
    /// Per texture level, coarsest first, the bytes written so far.
    texture_bytes: Vec<u64>,
}

impl std::fmt::Debug for Pyramid<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Pyramid")
            .field("tiles", &self.tiles)
            .field("levels", &self.levels)
            .finish_non_exhaustive()
    }
}

/// The carries of the children of tile row `y` of a pyramid's first level, one [`Parent`]
/// per column ([`Pyramid::above`]).
pub(super) type ChildrenFn<'a> = Box<dyn FnMut(u32) -> Result<Vec<Parent>, BuildError> + 'a>;

/// What a region job hands the merge ([`Pyramid::take_handover`]): the carries of its top
/// level's tiles, row-major, and the rows of the next coarser level that its top level's
/// rows make (each with its row number).
#[derive(Debug, Default)]
pub(super) struct Handover {
    pub carries: Vec<Carry>,
    pub rows: Vec<(u32, Vec<i32>)>,
    /// The next coarser level's raster, when there is one.
    up: Option<RasterSize>,
    /// Its next row to hand over.
    next_up_row: u32,
}

/// Makes tiles, from any thread.
struct TileMaker<'a> {
    context: TileContext<'a>,
    progress: ProgressFn<'a>,
    cancel: &'a AtomicBool,
    done: AtomicUsize,
    total: usize,
}

impl std::fmt::Debug for TileMaker<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TileMaker")
            .field("context", &self.context)
            .field("done", &self.done)
            .field("total", &self.total)
            .finish_non_exhaustive()
    }
}

/// One level being built.
#[derive(Debug)]
struct LevelState {
    level: u32,
    raster: RasterSize,
    grid: Grid,
    band: Band,
    next_tile_row: u32,
    /// One past the last tile row this pyramid makes of the level (the grid's rows but in a
    /// region job).
    end_tile_row: u32,
}

/// What a tile's children have handed up so far.
#[derive(Debug, Default)]
pub(super) struct Parent {
    /// North-west, north-east, south-west, south-east; `None` past the finer grid's edge.
    pub children: [Option<Carry>; 4],
}

/// A tile to make: its level and column (its row is the level's next), and above level 0
/// what its children handed up.
#[derive(Debug)]
struct Job {
    level: usize,
    x: u32,
    parent: Option<Parent>,
}

/// What a tile hands to its parent.
#[derive(Debug, Clone, PartialEq)]
pub(super) struct Carry {
    /// Bounds of the full-resolution surface under the tile.
    min_m: f32,
    max_m: f32,
    /// Largest vertical distance between the tile's own surface and the full-resolution
    /// surface, at every full-resolution sample under it (0 at level 0).
    deviation_m: f32,
    /// [`TileStats::half_resolution_error_m`].
    half_resolution_error_m: f32,
    /// The same of the padding that stands in for the siblings the tile lacks (see the
    /// module docs); 0 when it lacks none.
    padding_error_m: f32,
    texture: ChildTexture,
}

impl Carry {
    /// Appends the carry's bytes to `out`: its five figures as f32 bits (little-endian),
    /// then its texture ([`ChildTexture::write_to`]). Exact: a merge reads back what the
    /// region job held.
    pub fn write_to(&self, out: &mut Vec<u8>) {
        for v in [
            self.min_m,
            self.max_m,
            self.deviation_m,
            self.half_resolution_error_m,
            self.padding_error_m,
        ] {
            out.extend_from_slice(&v.to_le_bytes());
        }
        self.texture.write_to(out);
    }

    /// Reads what [`Carry::write_to`] wrote from the front of `bytes`, advancing it.
    pub fn read_from(bytes: &mut &[u8]) -> Option<Carry> {
        let mut figure = || -> Option<f32> {
            let (head, rest) = (bytes.len() >= 4).then(|| bytes.split_at(4))?;
            *bytes = rest;
            Some(f32::from_le_bytes(head.try_into().ok()?))
        };
        let [
            min_m,
            max_m,
            deviation_m,
            half_resolution_error_m,
            padding_error_m,
        ] = [figure()?, figure()?, figure()?, figure()?, figure()?];
        Some(Carry {
            min_m,
            max_m,
            deviation_m,
            half_resolution_error_m,
            padding_error_m,
            texture: ChildTexture::read_from(bytes)?,
        })
    }

    /// The same carry in allocations made by the calling thread.
    fn rehomed(self) -> Carry {
        Carry {
            texture: self.texture.clone(),
            ..self
        }
    }
}

/// One tile's output, made in parallel and written in order.
#[derive(Debug)]
struct MadeTile {
    carry: Carry,
    roughness_m: f32,
    /// The tile blob (mask errors, texture hashes, heights).
    blob: Vec<u8>,
    heights_bytes: u64,
    /// Encoded texture levels, coarsest first.
    texture_levels: Vec<Vec<u8>>,
}

impl<'a> Pyramid<'a> {
    /// The empty pyramid over a `raster` of level 0.
    pub fn new(
        raster: RasterSize,
        context: TileContext<'a>,
        progress: ProgressFn<'a>,
        cancel: &'a AtomicBool,
    ) -> Pyramid<'a> {
        let all = manifest::level_rasters(raster, context.tile_size).len();
        Pyramid::of_levels(raster, 0..all, None, None, context, progress, cancel)
    }

    /// A region job's pyramid: levels `0..=split` of the tiles under tile rows `rows` of
    /// level `split` (rows past the grid's end are ignored), with their
    /// [`Pyramid::take_handover`] for the merge. It reads level 0's rows from
    /// [`Pyramid::first_row`] on and is done ([`Pyramid::is_done`]) well before the last.
    pub fn region(
        raster: RasterSize,
        context: TileContext<'a>,
        split: u32,
        rows: std::ops::Range<u32>,
        progress: ProgressFn<'a>,
        cancel: &'a AtomicBool,
    ) -> Pyramid<'a> {
        let split = split as usize;
        let all = manifest::level_rasters(raster, context.tile_size);
        let up = all.get(split + 1).copied();
        let mut pyramid = Pyramid::of_levels(
            raster,
            0..(split + 1).min(all.len()),
            Some(rows),
            None,
            context,
            progress,
            cancel,
        );
        let step = pyramid.tiles.context.tile_size - 1;
        let first_up_row = pyramid
            .levels
            .last()
            .map_or(0, |l| l.next_tile_row * step / 2);
        pyramid.handover = Some(Handover {
            up,
            next_up_row: first_up_row,
            ..Handover::default()
        });
        pyramid
    }

    /// The merge's pyramid: the levels above `split`, level `split + 1` read row by row
    /// (from the region jobs' hand-overs) and its tiles made from `children`' carries.
    pub fn above(
        raster: RasterSize,
        context: TileContext<'a>,
        split: u32,
        children: ChildrenFn<'a>,
        progress: ProgressFn<'a>,
        cancel: &'a AtomicBool,
    ) -> Pyramid<'a> {
        let all = manifest::level_rasters(raster, context.tile_size).len();
        let first = (split as usize + 1).min(all);
        Pyramid::of_levels(
            raster,
            first..all,
            None,
            Some(children),
            context,
            progress,
            cancel,
        )
    }

    /// Levels `range` of the pyramid over a `raster` of level 0; with `region`, only the
    /// tiles under those tile rows of the range's last level.
    fn of_levels(
        raster: RasterSize,
        range: std::ops::Range<usize>,
        region: Option<std::ops::Range<u32>>,
        children: Option<ChildrenFn<'a>>,
        context: TileContext<'a>,
        progress: ProgressFn<'a>,
        cancel: &'a AtomicBool,
    ) -> Pyramid<'a> {
        let n = context.tile_size;
        let step = n - 1;
        let top = range.end.saturating_sub(1);
        let first = range.start;
        let levels: Vec<LevelState> = manifest::level_rasters(raster, n)
            .into_iter()
            .zip(0u32..)
            .skip(first)
            .take(range.len())
            .map(|(raster, level)| {
                // The first level stores its band and the halo; a coarser level only the rows
                // that outlive the finer band they are seen through (see `store_for`).
                let rows = if level as usize == first {
                    n + 2 * texture::GENERATED_HALO_ROWS
                } else {
                    (n - 1) / 2 + 1
                };
                let grid = Grid::covering(raster.width, raster.height, n);
                // Tile row `y` of the top level covers rows `2y` and `2y + 1` of the one below.
                let shift = top - level as usize;
                let (start, end) = match &region {
                    Some(rows) => (
                        (rows.start << shift).min(grid.rows),
                        (rows.end << shift).min(grid.rows),
                    ),
                    None => (0, grid.rows),
                };
                let mut band = Band::new(raster.width, raster.height, rows, context.code_range);
                if level as usize == first {
                    band.restart_at((start * step).saturating_sub(texture::GENERATED_HALO_ROWS));
                }
                LevelState {
                    level,
                    raster,
                    grid,
                    band,
                    next_tile_row: start,
                    end_tile_row: end.max(start),
                }
            })
            .collect();
        let total = levels
            .iter()
            .map(|l| (l.end_tile_row - l.next_tile_row) as usize * l.grid.columns as usize)
            .sum();
        Pyramid {
            tiles: TileMaker {
                context,
                progress,
                cancel,
                done: AtomicUsize::new(0),
                total,
            },
            pending: levels
                .iter()
                .enumerate()
                .map(|(i, l)| match i {
                    0 => Vec::new(),
                    _ => (0..l.grid.columns).map(|_| Parent::default()).collect(),
                })
                .collect(),
            records: levels
                .iter()
                .map(|l| {
                    let rows = (l.end_tile_row - l.next_tile_row) as usize;
                    Vec::with_capacity(rows * l.grid.columns as usize)
                })
                .collect(),
            levels,
            handover: None,
            children,
            heights_bytes: 0,
            texture_bytes: Vec::new(),
        }
    }

    /// The first row of its first level the pyramid reads ([`Pyramid::push_row`] takes rows
    /// from here on).
    pub fn first_row(&self) -> u32 {
        self.levels.first().map_or(0, |l| l.band.next_row())
    }

    /// Whether every tile row of every level is made: the rows still to come are not read.
    pub fn is_done(&self) -> bool {
        self.levels
            .iter()
            .all(|l| l.next_tile_row == l.end_tile_row)
    }

    /// What a region job made for the merge since the last call (see [`Handover`]).
    pub fn take_handover(&mut self) -> Handover {
        match &mut self.handover {
            Some(h) => Handover {
                carries: std::mem::take(&mut h.carries),
                rows: std::mem::take(&mut h.rows),
                up: h.up,
                next_up_row: h.next_up_row,
            },
            None => Handover::default(),
        }
    }

    /// Adds the next row of level 0 and makes every tile row that completes.
    pub fn push_row(&mut self, row: &[i32], writer: &mut dyn TileSink) -> Result<(), BuildError> {
        if self.tiles.cancel.load(Ordering::Relaxed) {
            return Err(BuildError::Cancelled);
        }
        if self.is_done() {
            return Ok(());
        }
        self.levels[0].band.push_row(row);
        while self.level_zero_ready() {
            self.make_climb(writer)?;
        }
        Ok(())
    }

    /// The levels, once every row of level 0 has been pushed.
    pub fn finish(self) -> Result<Built, BuildError> {
        let n = u64::from(self.tiles.context.tile_size);
        if let Some(level) = self
            .levels
            .iter()
            .find(|l| l.next_tile_row != l.end_tile_row)
        {
            return Err(BuildError::Unfinished {
                level: level.level,
                made: level.next_tile_row,
                rows: level.grid.rows,
            });
        }
        let tile_samples = self.tiles.total as u64 * n * n;
        let levels = self
            .levels
            .into_iter()
            .zip(self.records)
            .map(|(l, records)| Level {
                raster: l.raster,
                grid: GridSize {
                    columns: l.grid.columns,
                    rows: l.grid.rows,
                },
                tiles: records.into_iter().map(Written::record).collect(),
            })
            .collect();
        Ok(Built {
            levels,
            heights_bytes: self.heights_bytes,
            texture_bytes: self.texture_bytes.iter().sum(),
            texture_level_bytes: self.texture_bytes,
            tile_samples,
        })
    }

    /// Whether level 0 holds every row its next tile row reads, halo included.
    fn level_zero_ready(&self) -> bool {
        let level = &self.levels[0];
        let step = self.tiles.context.tile_size - 1;
        let j = level.next_tile_row;
        let last_needed =
            (j * step + step + texture::GENERATED_HALO_ROWS).min(level.raster.height - 1);
        j < level.end_tile_row && level.band.next_row() > last_needed
    }

    /// Makes level 0's next tile row and the coarser rows it completes (level `k + 1`'s when
    /// level `k`'s row is odd or its last); then, top down, lets each of those levels forget
    /// the rows its next tile row does not read, once the level above has stored what it
    /// still needs of them.
    fn make_climb(&mut self, writer: &mut dyn TileSink) -> Result<(), BuildError> {
        let mut top = 0;
        while top + 1 < self.levels.len() && completes_parents(&self.levels[top]) {
            top += 1;
        }
        self.make_rows(top, writer)?;
        if top + 1 == self.levels.len() {
            self.hand_over_rows();
        }
        for level in &mut self.levels[..=top] {
            level.next_tile_row += 1;
        }
        let step = self.tiles.context.tile_size - 1;
        for level in (0..=top).rev() {
            if level + 1 < self.levels.len() {
                self.store_for(level + 1);
            }
            let halo = if level == 0 {
                texture::GENERATED_HALO_ROWS
            } else {
                0
            };
            let l = &mut self.levels[level];
            l.band
                .drop_before((l.next_tile_row * step).saturating_sub(halo));
        }
        Ok(())
    }

    /// A region job's top level has just made a tile row: hands over the rows of the next
    /// coarser level it makes (every other sample of every other row of it, as `store_for`
    /// sees them), up to the row it shares with the next tile row, or to the last.
    fn hand_over_rows(&mut self) {
        let Some(handover) = &mut self.handover else {
            return;
        };
        let Some(up) = handover.up else {
            return;
        };
        let Some((level, finer)) = self.levels.split_last() else {
            return;
        };
        let step = self.tiles.context.tile_size - 1;
        let t = level.next_tile_row;
        let last = if t + 1 == level.grid.rows {
            up.height - 1
        } else {
            ((t + 1) * step / 2).min(up.height - 1)
        };
        while handover.next_up_row <= last {
            let y = handover.next_up_row;
            let seen = level_row(finer, level, 2 * y).halved(up.width);
            handover
                .rows
                .push((y, (0..seen.len()).map(|x| seen.get(x)).collect()));
            handover.next_up_row += 1;
        }
    }

    /// Stores in level `k`'s band the rows its next tile row reads that it sees through
    /// level `k - 1`'s rows, which that level is about to forget (those above its next tile
    /// row, halo aside). The level above a band's top half thus keeps it until its bottom
    /// half arrives, and sees the bottom half through the finer band when it makes the row.
    fn store_for(&mut self, k: usize) {
        let step = self.tiles.context.tile_size - 1;
        let (finer, coarser) = self.levels.split_at_mut(k);
        let coarse = &mut coarser[0];
        let Some((fine, below)) = finer.split_last() else {
            return;
        };
        if coarse.next_tile_row == coarse.end_tile_row {
            return;
        }
        let halo = if k == 1 {
            texture::GENERATED_HALO_ROWS
        } else {
            0
        };
        let fine_keeps = (fine.next_tile_row * step).saturating_sub(halo);
        let needed = coarse.next_tile_row * step;
        let from = needed.max(coarse.band.next_row());
        let band = &mut coarse.band;
        if band.next_row() < from {
            band.restart_at(from);
        }
        band.drop_before(needed);
        let mut row = Vec::with_capacity(coarse.raster.width as usize);
        for y in from..coarse.raster.height {
            let fine_y = (2 * y).min(fine.raster.height - 1);
            if fine_y >= fine_keeps {
                break;
            }
            row.clear();
            let seen = level_row(below, fine, fine_y).halved(coarse.raster.width);
            row.extend((0..seen.len()).map(|x| seen.get(x)));
            band.push_row(&row);
        }
    }

    /// Makes and writes the next tile row of levels `0..=top`.
    ///
    /// Tiles are made on rayon's threads, a few at a time, and written on this one in row
    /// order per level as soon as those before them are. A parent is queued as soon as its
    /// last child is written, ahead of the finer level's remaining tiles: so a row's outputs
    /// are never all held, and of the carries only those of the north children wait, for
    /// the south row.
    fn make_rows(&mut self, top: usize, writer: &mut dyn TileSink) -> Result<(), BuildError> {
        let first_parents = match &mut self.children {
            Some(children) => Some(children(self.levels[0].next_tile_row)?),
            None => None,
        };
        let (levels, tiles) = (&self.levels[..], &self.tiles);
        let mut output = Output {
            top,
            writer,
            handover: self.handover.as_mut().map(|h| &mut h.carries),
            pending: &mut self.pending,
            records: &mut self.records,
            heights_bytes: &mut self.heights_bytes,
            texture_bytes: &mut self.texture_bytes,
            failure: None,
        };
        let window = 2 * rayon::current_num_threads();
        let stop = AtomicBool::new(false);
        rayon::in_place_scope(|scope| {
            let (sender, receiver) = std::sync::mpsc::channel();
            let spawn = |job: Job| {
                let (sender, stop) = (sender.clone(), &stop);
                scope.spawn(move |_| {
                    let level = &levels[job.level];
                    let id = TileId::at(level.level, job.x, level.next_tile_row);
                    let made = if stop.load(Ordering::Relaxed) {
                        Err(BuildError::Cancelled)
                    } else {
                        let (finer, level) = (&levels[..job.level], &levels[job.level]);
                        tiles.make(finer, level, id, job.parent)
                    };
                    // The receiver outlives every sender: it is read until the last job ends.
                    let _ = sender.send((job.level, job.x, made));
                });
            };
            let mut queue = Queue::new(levels[0].grid.columns, first_parents);
            let mut in_order = InOrder::new(top);
            let mut in_flight = 0;
            loop {
                while output.failure.is_none() && in_flight < window {
                    let Some(job) = queue.next() else { break };
                    spawn(job);
                    in_flight += 1;
                }
                let Some((k, x, made)) = (in_flight > 0).then(|| receiver.recv().ok()).flatten()
                else {
                    break;
                };
                in_flight -= 1;
                for (x, made) in in_order.accept(k, x, made) {
                    queue.ready.extend(output.write(k, &levels[k], x, made));
                }
                if output.failure.is_some() {
                    stop.store(true, Ordering::Relaxed);
                }
            }
        });
        output.failure.map_or(Ok(()), Err)
    }
}

/// The jobs of a climb not yet started: parents ready to make, then level 0's tiles.
#[derive(Debug)]
struct Queue {
    ready: std::collections::VecDeque<Job>,
    next_at_level_zero: u32,
    columns_at_level_zero: u32,
    /// Above a split level, the first level's tiles' children ([`Pyramid::above`]).
    first_parents: Option<std::vec::IntoIter<Parent>>,
}

impl Queue {
    fn new(columns_at_level_zero: u32, first_parents: Option<Vec<Parent>>) -> Queue {
        Queue {
            ready: std::collections::VecDeque::new(),
            next_at_level_zero: 0,
            columns_at_level_zero,
            first_parents: first_parents.map(Vec::into_iter),
        }
    }

    /// A ready parent first: making it frees its children's carries.
    fn next(&mut self) -> Option<Job> {
        self.ready.pop_front().or_else(|| {
            let x = self.next_at_level_zero;
            (x < self.columns_at_level_zero).then(|| {
                self.next_at_level_zero += 1;
                Job {
                    level: 0,
                    x,
                    parent: self
                        .first_parents
                        .as_mut()
                        .map(|p| p.next().unwrap_or_default()),
                }
            })
        })
    }
}

/// Made tiles, put back in row order per level.
#[derive(Debug)]
struct InOrder {
    /// Per level, the next column to hand out, and the tiles made ahead of it.
    next: Vec<u32>,
    early: Vec<std::collections::BTreeMap<u32, Result<MadeTile, BuildError>>>,
}

impl InOrder {
    fn new(top: usize) -> InOrder {
        InOrder {
            next: vec![0; top + 1],
            early: (0..=top)
                .map(|_| std::collections::BTreeMap::new())
                .collect(),
        }
    }

    /// Takes tile `x` of level `k`; returns the tiles of that level now in order.
    fn accept(
        &mut self,
        k: usize,
        x: u32,
        made: Result<MadeTile, BuildError>,
    ) -> Vec<(u32, Result<MadeTile, BuildError>)> {
        self.early[k].insert(x, made);
        let mut run = Vec::new();
        while let Some(made) = self.early[k].remove(&self.next[k]) {
            run.push((self.next[k], made));
            self.next[k] += 1;
        }
        run
    }
}

/// The writing side of a climb: the database, the records, and the parents' carries.
#[derive(Debug)]
struct Output<'a> {
    /// The highest level the climb makes a row of.
    top: usize,
    writer: &'a mut dyn TileSink,
    /// A region job's top-level carries, kept for the merge.
    handover: Option<&'a mut Vec<Carry>>,
    pending: &'a mut [Vec<Parent>],
    records: &'a mut [Vec<Written>],
    heights_bytes: &'a mut u64,
    /// Per texture level, coarsest first.
    texture_bytes: &'a mut Vec<u64>,
    /// The first error, after which nothing more is written.
    failure: Option<BuildError>,
}

impl Output<'_> {
    /// Writes tile `x` of `level`'s row and hands its carry to its parent; returns the
    /// parent's job when this was its last child and the climb makes the parent's row.
    fn write(
        &mut self,
        k: usize,
        level: &LevelState,
        x: u32,
        made: Result<MadeTile, BuildError>,
    ) -> Option<Job> {
        if self.failure.is_some() {
            return None;
        }
        let written = made.and_then(|made| {
            *self.heights_bytes += made.heights_bytes;
            let (record, carry) = write(level.level, made, self.writer, self.texture_bytes)?;
            self.records[k].push(record);
            Ok(carry)
        });
        let carry = match written {
            Ok(carry) => carry,
            Err(error) => {
                self.failure = Some(error);
                return None;
            }
        };
        let Some(parents) = self.pending.get_mut(k + 1) else {
            if let Some(handover) = &mut self.handover {
                handover.push(carry);
            }
            return None;
        };
        let parent = parents.get_mut(x as usize / 2)?;
        let j = level.next_tile_row;
        parent.children[x as usize % 2 + 2 * (j as usize % 2)] = Some(carry);
        let last_child = x % 2 == 1 || x + 1 == level.grid.columns;
        (k < self.top && last_child).then(|| Job {
            level: k + 1,
            x: x / 2,
            parent: Some(std::mem::take(parent)),
        })
    }
}

/// Whether a level's next tile row completes its parents' children: an odd row, or its last.
fn completes_parents(level: &LevelState) -> bool {
    let j = level.next_tile_row;
    j % 2 == 1 || j + 1 == level.grid.rows
}

/// Row `y` of `level` (the last row for `y` past it): stored in its band, or seen through
/// the levels below it (`finer`, finest first), every other sample of the finer level's row
/// `2y`, as [`tiles::decimate`] makes it.
fn level_row<'a>(finer: &'a [LevelState], level: &'a LevelState, y: u32) -> tiles::Row<'a> {
    let y = y.min(level.raster.height - 1);
    match finer.split_last() {
        Some((fine, below)) if !level.band.holds(y) => {
            let fine_y = (2 * y).min(fine.raster.height - 1);
            level_row(below, fine, fine_y).halved(level.raster.width)
        }
        _ => level.band.row(y),
    }
}

/// Tile `id` of `level`, its rows seen through the levels below it where need be.
fn cut_tile(
    finer: &[LevelState],
    level: &LevelState,
    id: TileId,
    metres: (f64, f64),
) -> tiles::TileSamples {
    let (width, height) = (level.raster.width, level.raster.height);
    let row = |y| level_row(finer, level, y);
    tiles::cut_with(row, width, height, level.grid, id, metres)
}

/// A written tile's record, its hash as bytes: the manifest's [`TileRecord`] holds it as a
/// string, twice the size and an allocation of its own, for every tile of the pyramid.
#[derive(Debug, Clone, Copy)]
struct Written {
    hash: [u8; 16],
    bytes: u64,
    coarsest_texture_bytes: u64,
    min_m: f32,
    max_m: f32,
    roughness_m: f32,
}

impl Written {
    fn record(self) -> TileRecord {
        TileRecord {
            hash: self.hash.iter().map(|b| format!("{b:02x}")).collect(),
            bytes: self.bytes,
            coarsest_texture_bytes: self.coarsest_texture_bytes,
            min_m: self.min_m,
            max_m: self.max_m,
            roughness_m: self.roughness_m,
        }
    }
}

/// The bytes of a 32-digit hex hash ([`manifest::content_hash`] makes nothing else).
fn hash_bytes(hex: &str) -> [u8; 16] {
    std::array::from_fn(|i| {
        hex.get(2 * i..2 * i + 2)
            .and_then(|pair| u8::from_str_radix(pair, 16).ok())
            .unwrap_or(0)
    })
}

/// Writes a made tile to level `level`'s files, adding its textures' bytes to
/// `texture_bytes` (per texture level); returns its record and its carry.
fn write(
    level: u32,
    made: MadeTile,
    writer: &mut dyn TileSink,
    texture_bytes: &mut Vec<u64>,
) -> Result<(Written, Carry), BuildError> {
    let stored = writer.add_level_heights(level, &made.blob)?;
    if texture_bytes.len() < made.texture_levels.len() {
        texture_bytes.resize(made.texture_levels.len(), 0);
    }
    for (total, encoded) in texture_bytes.iter_mut().zip(&made.texture_levels) {
        *total += writer.add_level_texture(level, encoded)?.bytes;
    }
    let record = Written {
        hash: hash_bytes(&stored.hash),
        bytes: stored.bytes,
        coarsest_texture_bytes: made.texture_levels.first().map_or(0, |t| t.len() as u64),
        min_m: made.carry.min_m,
        max_m: made.carry.max_m,
        roughness_m: made.roughness_m,
    };
    // The carry lives until the parent is made, rows later: copied here, on the writing
    // thread, it leaves the worker's arena to the buffers of one tile at a time.
    Ok((record, made.carry.rehomed()))
}

impl TileMaker<'_> {
    /// Cuts, measures, textures and encodes tile `id` of `level`, whose rows it sees through
    /// the `finer` levels (finest first) where it does not store them.
    fn make(
        &self,
        finer: &[LevelState],
        level: &LevelState,
        id: TileId,
        parent: Option<Parent>,
    ) -> Result<MadeTile, BuildError> {
        if self.cancel.load(Ordering::Relaxed) {
            return Err(BuildError::Cancelled);
        }
        let c = &self.context;
        let metres = (c.quantum_m, c.offset_m);
        let cut = cut_tile(finer, level, id, metres);
        let encoded = cut
            .heights
            .encode_with(c.heights_coder)
            .map_err(|source| BuildError::Encode { tile: id, source })?;
        let mut stats = tiles::stats(&cut);
        let (finest, deviation_m) = match parent {
            Some(parent) if level.level > 0 => {
                let finest = texture::from_children(&parent.textures(), c.texture_size)
                    .map_err(|e| BuildError::TextureEncode(e.to_string()))?;
                (finest, parent.fold_into(&mut stats))
            }
            _ => (self.level_zero_texture(level, id)?, 0.0),
        };
        // The siblings this tile lacks: their padding is cut from the rows it stands on, which
        // are held now and may not be when the parent is made.
        let missing = level.grid.missing_siblings(id.x, id.y);
        let padding_error_m = missing
            .ids(id)
            .map(|sibling| tiles::half_resolution_error(&cut_tile(finer, level, sibling, metres)))
            .fold(0.0, f32::max);
        tiles::add_deviation(&mut stats.mask_errors_m, deviation_m);
        let edges = Edges::for_missing(missing, c.texture_size);
        let carried_texture = ChildTexture::of(&finest, edges)
            .map_err(|e| BuildError::TextureEncode(e.to_string()))?;
        let texture_levels = texture::mip_chain(finest)
            .iter()
            .map(|level| texture::encode(level, c.texture_format, c.jpeg_quality))
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| BuildError::TextureEncode(e.to_string()))?;
        let blob = TileBlob {
            mask_errors_m: stats.mask_errors_m,
            texture: texture_levels
                .iter()
                .map(|l| manifest::Blob::of(l))
                .collect(),
            heights: encoded,
        };
        (self.progress)(self.done.fetch_add(1, Ordering::Relaxed) + 1, self.total);
        Ok(MadeTile {
            carry: Carry {
                min_m: stats.min_m,
                max_m: stats.max_m,
                deviation_m,
                half_resolution_error_m: stats.half_resolution_error_m,
                padding_error_m,
                texture: carried_texture,
            },
            roughness_m: stats.roughness_m,
            blob: blob.encode(),
            heights_bytes: blob.heights.len() as u64,
            texture_levels,
        })
    }

    /// The finest texture of tile `id` of level 0.
    fn level_zero_texture(&self, level: &LevelState, id: TileId) -> Result<RgbImage, BuildError> {
        let c = &self.context;
        let grid = level.grid;
        Ok(match &c.level_zero_texture {
            LevelZeroTexture::Image {
                image,
                registration,
                raster,
            } => texture::from_image(image, *registration, *raster, grid, id, c.texture_size),
            LevelZeroTexture::Generated {
                spacing_m,
                min_m,
                max_m,
            } => {
                let field = HeightField {
                    band: &level.band,
                    quantum_m: c.quantum_m,
                    offset_m: c.offset_m,
                    spacing_m: *spacing_m,
                    min_m: *min_m,
                    max_m: *max_m,
                };
                texture::generated(&field, grid, id, c.texture_size)
            }
            LevelZeroTexture::FromChildren => {
                return Err(BuildError::TextureEncode(format!(
                    "tile {id} has no children to filter its texture from"
                )));
            }
        })
    }
}

impl Parent {
    fn textures(&self) -> [Option<&ChildTexture>; 4] {
        self.children
            .each_ref()
            .map(|c| c.as_ref().map(|c| &c.texture))
    }

    /// Widens `stats`' bounds to the children's (the full-resolution surface under the
    /// tile) and returns the tile's distance from full resolution: its children's largest,
    /// plus its own decimation error (the largest of its children's half-resolution errors,
    /// and of the padding's; see the module docs).
    fn fold_into(&self, stats: &mut TileStats) -> f32 {
        let children = || self.children.iter().flatten();
        for child in children() {
            stats.min_m = stats.min_m.min(child.min_m);
            stats.max_m = stats.max_m.max(child.max_m);
        }
        let below = children().map(|c| c.deviation_m).fold(0.0, f32::max);
        let decimation = children()
            .map(|c| c.half_resolution_error_m.max(c.padding_error_m))
            .fold(0.0, f32::max);
        below + decimation
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::build::{BuildOptions, TextureChoice, build};
    use crate::db::{TileDb, Verify};
    use std::path::{Path, PathBuf};
    use terrain_shared::Heights;

    const OFFSET_M: f64 = -20.0;
    const TEXTURE_SIZE: u32 = 16;

    /// Codes of a `width x height` raster: hills and a ridge, rough enough that every
    /// decimation loses something.
    fn terrain(width: u32, height: u32) -> Vec<i32> {
        (0..height)
            .flat_map(|y| (0..width).map(move |x| (x, y)))
            .map(|(x, y)| {
                let (x, y) = (f64::from(x), f64::from(y));
                let hills = 300.0 * (x / 5.0).sin() * (y / 7.0).cos();
                let ridge = 400.0 / (1.0 + ((x - 1.5 * y) / 4.0).powi(2));
                let roughness = f64::from((x as u32 * 7919 + y as u32 * 104_729) % 23);
                (1000.0 + hills + ridge + roughness) as i32
            })
            .collect()
    }

    /// The quantum of float samples the builder is left with: its default.
    const FLOAT_QUANTUM_M: f64 = crate::build::DEFAULT_FLOAT_QUANTUM_M;

    /// Writes `codes` as the input of a build: a 16-bit PNG, or (codes at
    /// [`FLOAT_QUANTUM_M`]) a float32 GeoTIFF, whose codes may span more than 16 bits and
    /// then are held 32 bits a sample.
    fn write_input(dir: &Path, codes: &[i32], width: u32, height: u32, quantum_m: f64) -> PathBuf {
        if quantum_m == FLOAT_QUANTUM_M {
            let path = dir.join("terrain.tif");
            let metres: Vec<f32> = codes
                .iter()
                .map(|&c| (f64::from(c) * quantum_m) as f32)
                .collect();
            let file = std::fs::File::create(&path).expect("create the input");
            let mut encoder = tiff::encoder::TiffEncoder::new(file).expect("encoder");
            encoder
                .write_image::<tiff::encoder::colortype::Gray32Float>(width, height, &metres)
                .expect("write the input");
            return path;
        }
        let path = dir.join("terrain.png");
        let raw: Vec<u16> = codes.iter().map(|&c| c as u16).collect();
        image::ImageBuffer::<image::Luma<u16>, _>::from_raw(width, height, raw)
            .expect("size")
            .save(&path)
            .expect("write the input");
        path
    }

    /// Every level of the raster, each the whole raster, as the definitions make them.
    fn whole_levels(codes: Vec<i32>, raster: RasterSize, n: u32) -> Vec<(RasterSize, Vec<i32>)> {
        let rasters = manifest::level_rasters(raster, n);
        let mut levels = vec![(raster, codes)];
        for pair in rasters.windows(2) {
            let (from, to) = (pair[0], pair[1]);
            let finer = &levels[levels.len() - 1].1;
            let coarser = tiles::decimate(finer, from, to);
            levels.push((to, coarser));
        }
        levels
    }

    /// What a tile must be, computed from whole rasters.
    struct Expected {
        codes: Vec<i32>,
        min_m: f32,
        max_m: f32,
        mask_errors_m: Vec<f32>,
        /// Distance from full resolution, and the finest texture.
        deviation_m: f32,
        finest: RgbImage,
    }

    /// Tile `id` from the whole rasters of its level and those below (`below[level]`: the
    /// expected tiles of the finer levels, row-major).
    fn expected(
        levels: &[(RasterSize, Vec<i32>)],
        below: &[Vec<Expected>],
        id: TileId,
        (n, quantum_m): (u32, f64),
    ) -> Expected {
        let k = id.level as usize;
        let (raster, codes) = &levels[k];
        let grid = Grid::covering(raster.width, raster.height, n);
        let cut = tiles::cut(
            codes,
            raster.width,
            raster.height,
            grid,
            id,
            quantum_m,
            OFFSET_M,
        );
        let stats = tiles::stats(&cut);
        // Bounds: the full-resolution samples under the tile.
        let (full, full_codes) = &levels[0];
        let span = (n - 1) << k;
        let columns = (id.x * span).min(full.width - 1)..=((id.x + 1) * span).min(full.width - 1);
        let rows = (id.y * span).min(full.height - 1)..=((id.y + 1) * span).min(full.height - 1);
        let metres: Vec<f32> = rows
            .flat_map(|y| columns.clone().map(move |x| (x, y)))
            .map(|(x, y)| full_codes[(y * full.width + x) as usize])
            .map(|c| (OFFSET_M + quantum_m * f64::from(c)) as f32)
            .collect();
        let min_m = metres.iter().copied().fold(f32::MAX, f32::min);
        let max_m = metres.iter().copied().fold(f32::MIN, f32::max);
        let (deviation_m, finest) = if k == 0 {
            let band = Band::whole(codes, raster.width, raster.height);
            let (low, high) = codes
                .iter()
                .fold((i32::MAX, i32::MIN), |(l, h), &c| (l.min(c), h.max(c)));
            let field = HeightField {
                band: &band,
                quantum_m,
                offset_m: OFFSET_M,
                spacing_m: [1.0, 1.0],
                min_m: OFFSET_M + quantum_m * f64::from(low),
                max_m: OFFSET_M + quantum_m * f64::from(high),
            };
            (0.0, texture::generated(&field, grid, id, TEXTURE_SIZE))
        } else {
            let (finer, _) = &levels[k - 1];
            let finer_grid = Grid::covering(finer.width, finer.height, n);
            let children: Vec<Option<&Expected>> = id
                .children()
                .into_iter()
                .flatten()
                .map(|c| {
                    (c.x < finer_grid.columns && c.y < finer_grid.rows)
                        .then(|| &below[k - 1][(c.y * finer_grid.columns + c.x) as usize])
                })
                .collect();
            let deepest = children
                .iter()
                .flatten()
                .map(|c| c.deviation_m)
                .fold(0.0, f32::max);
            let decimation =
                tiles::decimation_error(&levels[k - 1].1, *finer, id, n, quantum_m, OFFSET_M);
            let textures: Vec<Option<&RgbImage>> =
                children.iter().map(|c| c.map(|c| &c.finest)).collect();
            (
                deepest + decimation,
                texture::filter_mosaic(&textures, TEXTURE_SIZE),
            )
        };
        let mut mask_errors_m = stats.mask_errors_m;
        tiles::add_deviation(&mut mask_errors_m, deviation_m);
        Expected {
            codes: cut.heights.codes,
            min_m,
            max_m,
            mask_errors_m,
            deviation_m,
            finest,
        }
    }

    /// Builds a `width x height` raster of `codes` (metres: `quantum_m` a code) with
    /// `n`-sample tiles and checks every tile of every level against its computation from
    /// whole rasters: heights, bounds, mask errors (the distance from full resolution
    /// included) and textures.
    fn check_levels_against_whole_rasters(
        codes: Vec<i32>,
        width: u32,
        height: u32,
        n: u32,
        quantum_m: f64,
    ) {
        let dir = tempfile::tempdir().expect("temporary directory");
        let input = write_input(dir.path(), &codes, width, height, quantum_m);
        let mut options = BuildOptions::new(&input, dir.path().join("db"));
        options.tile_size = n;
        // A PNG's codes are metres once scaled; a float raster's samples are metres already.
        let float = input.extension().is_some_and(|e| e == "tif");
        options.height_scale = Some(if float { 1.0 } else { quantum_m });
        options.height_offset = Some(OFFSET_M);
        options.texture = TextureChoice::Generated;
        options.texture_size = Some(TEXTURE_SIZE);
        options.texture_format = ImageFormat::Png;
        let report = build(&options, &|_, _| {}, &AtomicBool::new(false)).expect("builds");
        let mut files: Vec<String> = std::fs::read_dir(&report.out)
            .expect("the database")
            .map(|e| e.expect("entry").file_name().to_string_lossy().into_owned())
            .collect();
        files.sort();
        assert_eq!(files, ["heights.pack", "manifest.json", "textures.pack"]);
        let db = TileDb::open(&report.out, Verify::Hashes).expect("opens");
        let levels = whole_levels(codes, RasterSize { width, height }, n);
        assert_eq!(db.manifest().level_count() as usize, levels.len());
        let mut made: Vec<Vec<Expected>> = Vec::new();
        for (k, (raster, _)) in levels.iter().enumerate() {
            let grid = Grid::covering(raster.width, raster.height, n);
            let tiles: Vec<Expected> = grid
                .tiles()
                .map(|t| {
                    expected(
                        &levels,
                        &made,
                        TileId::at(k as u32, t.x, t.y),
                        (n, quantum_m),
                    )
                })
                .collect();
            for (t, want) in grid.tiles().zip(&tiles) {
                let id = TileId::at(k as u32, t.x, t.y);
                let stored = db.heights(id).expect("tile");
                let blob = TileBlob::decode(&stored.bytes).expect("blob");
                let heights = Heights::decode(&blob.heights).expect("heights");
                assert_eq!(heights.codes, want.codes, "{id} heights");
                let record =
                    db.manifest().levels[k].tiles[(t.y * grid.columns + t.x) as usize].clone();
                assert_eq!(
                    (record.min_m, record.max_m),
                    (want.min_m, want.max_m),
                    "{id} bounds"
                );
                assert_eq!(blob.mask_errors_m, want.mask_errors_m, "{id} mask errors");
                let textures: Vec<manifest::Blob> = texture::mip_chain(want.finest.clone())
                    .iter()
                    .map(|l| {
                        manifest::Blob::of(&texture::encode(l, ImageFormat::Png, 85).expect("png"))
                    })
                    .collect();
                assert_eq!(blob.texture, textures, "{id} textures");
            }
            made.push(tiles);
        }
    }

    #[test]
    fn a_build_cancelled_midway_leaves_nothing_behind() {
        let dir = tempfile::tempdir().expect("temporary directory");
        let input = dir.path().join("terrain.png");
        let (width, height) = (70, 60);
        let raw: Vec<u16> = terrain(width, height).iter().map(|&c| c as u16).collect();
        image::ImageBuffer::<image::Luma<u16>, _>::from_raw(width, height, raw)
            .expect("size")
            .save(&input)
            .expect("write the input");
        let out = dir.path().join("db");
        let mut options = BuildOptions::new(&input, &out);
        options.tile_size = 9;
        // Cancelled from the progress callback once a few tiles are made, as Ctrl-C would.
        let cancel = AtomicBool::new(false);
        let (most, total) = (AtomicUsize::new(0), AtomicUsize::new(0));
        let progress = |done: usize, all: usize| {
            most.fetch_max(done, Ordering::Relaxed);
            total.store(all, Ordering::Relaxed);
            if done == 5 {
                cancel.store(true, Ordering::Relaxed);
            }
        };
        let result = build(&options, &progress, &cancel);
        assert!(matches!(result, Err(BuildError::Cancelled)), "{result:?}");
        let (most, total) = (most.into_inner(), total.into_inner());
        assert!(most < total / 2, "stopped after {most} of {total} tiles");
        let left: Vec<_> = std::fs::read_dir(dir.path())
            .expect("the directory")
            .map(|e| e.expect("entry").file_name())
            .collect();
        assert_eq!(left, ["terrain.png"], "only the input is left");
    }

    #[test]
    fn every_level_matches_its_computation_from_whole_rasters() {
        // Sizes that are not multiples of the tile step, with odd numbers of tile columns
        // and rows at some levels (the padding children).
        for (width, height, n) in [(45, 38, 9), (41, 50, 9), (70, 17, 5), (9, 9, 9)] {
            check_levels_against_whole_rasters(terrain(width, height), width, height, n, 0.5);
        }
        // Float heights in centimetres: codes spanning 17 bits, held as they are.
        let (width, height) = (45, 38);
        let centimetres = terrain(width, height)
            .iter()
            .map(|c| 100 * c + c % 7)
            .collect();
        check_levels_against_whole_rasters(centimetres, width, height, 9, FLOAT_QUANTUM_M);
    }

    /// Heights `low < high` (codes at `quantum_m`) for which the two triangles of a cell
    /// round the midpoint between them differently: `high` and `low` so far apart that their
    /// difference is inexact in f32. The first such pair, searched for rather than written
    /// down, so the case follows the arithmetic.
    fn inexact_midpoint(quantum_m: f64) -> (i32, i32) {
        let metres = |c: i32| (OFFSET_M + quantum_m * f64::from(c)) as f32;
        (201..400)
            .flat_map(|low| (20_000..20_400).map(move |high| (low, high)))
            .find(|&(low, high)| {
                let (t, b) = (metres(low), metres(high));
                // The left edge of a cell whose columns repeat (first triangle) and the
                // right edge of one (second triangle), half-way down.
                terrain_shared::mask::cell_height(t, t, b, b, 0.0, 0.5)
                    < terrain_shared::mask::cell_height(t, t, b, b, 1.0, 0.5)
            })
            .expect("f32 rounds some midpoint differently")
    }

    #[test]
    fn a_padding_child_can_hold_its_parents_decimation_error() {
        // 13 x 5 samples in tiles of 5: three tile columns, so the parent of the third has
        // a padding child east of it, which repeats the last column. Every column rises
        // from a low height to a high one; the last has a bump half-way, which is the
        // parent's largest error. The real child measures it with the second triangle of
        // its last cell, the padding child also with the first, which rounds the midpoint
        // lower: its error is an f32 step larger, and it is the parent's.
        let quantum_m = 0.1;
        let (low, high) = inexact_midpoint(quantum_m);
        let middle = (low + high) / 2;
        // A few metres above the midpoint: an error far smaller than the heights keeps the
        // f32 step between the two interpolations.
        let spike = middle + 50;
        let (width, height) = (13u32, 5u32);
        let codes = (0..height)
            .flat_map(|y| (0..width).map(move |x| (x, y)))
            .map(|(x, y)| match (y, x + 1 == width) {
                (0, _) => low,
                (1, false) => middle,
                (1, true) => spike,
                _ => high,
            })
            .collect();
        check_levels_against_whole_rasters(codes, width, height, 5, quantum_m);
    }
}
