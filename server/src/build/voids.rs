//! Filling no-data voids, region by region, with a thin-plate membrane that meets the
//! surrounding terrain on every side (SRTM voids are -32768 m; no void may reach a tile as
//! a spike).
//!
//! **The membrane.** A void region (8-connected void samples) is filled with the surface
//! that bends least: the heights of its samples minimise the sum over the region and its
//! rim of the squared discrete Laplacian (the 5-point stencil), the known samples within
//! [`RIM`] of the region held fixed. That is the thin-plate (biharmonic) interpolation GIS
//! tools offer: smooth inside, no terraces or flat plateaus where fronts from different rims
//! meet (the wave fill it replaces carried rim heights inwards and stepped by up to 2,674 m
//! inside one Everest void), and exact on planes and paraboloids, whose Laplacian is
//! constant. It is solved by conjugate gradients on the normal equations, started from the
//! harmonic membrane (the mean of the neighbours, solved the same way), to a residual of
//! [`TOLERANCE`] code steps.
//!
//! **Bounded memory.** Regions are found in a pass over the rows that holds one row of run
//! labels ([`Labeler`]: union-find over runs of void samples, deterministic, so a later
//! pass that labels the same rows again finds each run's region without looking ahead);
//! each region is then solved in its window (its bounding box and the rim) while the rows
//! pass, holding only the windows of the regions the current row crosses, and its filled
//! codes wait in an anonymous temporary file ([`Store`]) until the build's own pass puts
//! them in place ([`FillStream`]). So a raster with voids is never held whole; what is held
//! grows with its largest void (and a few bytes per void region), not with the raster. A raster read whole ([`fill`]) is filled by the
//! same passes over its rows, so the database does not depend on how it was read.

use std::collections::HashMap;

/// Known samples within this many of a void region take part in its membrane: two, the
/// reach of the 5-point Laplacian of a neighbour of the region.
pub const RIM: u32 = 2;
/// The membrane is solved until no equation is off by more than this, in code steps.
pub const TOLERANCE: f64 = 1e-3;
/// Conjugate-gradient iterations a region may take, per sample of its window's larger
/// side, squared: the thin plate's conditioning grows with the fourth power of the window's
/// size, the iterations CG needs with its square. Past it the membrane stops where it is
/// (and says so in the report).
const ITERATIONS_PER_SIDE_SQUARED: usize = 16;

/// What filling did, for the build's warnings.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FillReport {
    pub samples: usize,
    /// Connected (8-neighbour) void regions.
    pub regions: usize,
    pub largest_region: usize,
    /// Regions whose membrane stopped at the iteration cap before [`TOLERANCE`].
    pub unconverged: usize,
}

/// A run of void samples in a row, `start..end`, and its provisional label.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Run {
    pub start: u32,
    pub end: u32,
    pub label: u32,
}

/// Labels the void runs of rows pushed one after another, north first, 8-connected: a
/// run takes the label of the first run of the row above that touches it (diagonally too),
/// and any other such run is merged with it. Deterministic: the same rows give the same
/// labels, which is what lets a later pass find each run's region as the rows arrive.
#[derive(Debug, Clone, Default)]
pub struct Labeler {
    above: Vec<Run>,
    parent: Vec<u32>,
    /// Per label, the bounding box of its runs so far (x0, y0, x1, y1 inclusive) and its
    /// samples; merged into the root's at the end.
    boxes: Vec<[u32; 4]>,
    samples: Vec<u64>,
    y: u32,
}

impl Labeler {
    pub fn new() -> Labeler {
        Labeler::default()
    }

    /// Labels the runs of `voids`, the next row.
    pub fn push(&mut self, voids: &[bool]) -> Vec<Run> {
        let mut runs = Vec::new();
        let mut x = 0;
        while x < voids.len() {
            if !voids[x] {
                x += 1;
                continue;
            }
            let start = x;
            while x < voids.len() && voids[x] {
                x += 1;
            }
            let (start, end) = (start as u32, x as u32);
            let mut label = None;
            let above_runs = std::mem::take(&mut self.above);
            for above in &above_runs {
                // 8-connected: touching columns, diagonals included.
                if above.end + 1 > start && above.start < end + 1 {
                    let root = self.find(above.label);
                    match label {
                        None => label = Some(root),
                        Some(l) if l != root => {
                            let (keep, merged) = (l.min(root), l.max(root));
                            self.parent[merged as usize] = keep;
                            label = Some(keep);
                        }
                        Some(_) => {}
                    }
                }
            }
            self.above = above_runs;
            let label = label.unwrap_or_else(|| {
                self.parent.push(self.parent.len() as u32);
                self.boxes.push([start, self.y, end - 1, self.y]);
                self.samples.push(0);
                self.parent.len() as u32 - 1
            });
            let b = &mut self.boxes[label as usize];
            *b = [
                b[0].min(start),
                b[1].min(self.y),
                b[2].max(end - 1),
                b[3].max(self.y),
            ];
            self.samples[label as usize] += u64::from(end - start);
            runs.push(Run { start, end, label });
        }
        self.above.clone_from(&runs);
        self.y += 1;
        runs
    }

    fn find(&mut self, mut label: u32) -> u32 {
        while self.parent[label as usize] != label {
            let grand = self.parent[self.parent[label as usize] as usize];
            self.parent[label as usize] = grand;
            label = grand;
        }
        label
    }

    /// The regions: each label's final region, and each region's box and samples.
    pub fn finish(mut self) -> Regions {
        let labels = self.parent.len();
        let mut index: HashMap<u32, usize> = HashMap::new();
        let mut regions: Vec<Region> = Vec::new();
        let mut region_of = Vec::with_capacity(labels);
        for label in 0..labels as u32 {
            let root = self.find(label);
            let next = regions.len();
            let r = *index.entry(root).or_insert(next);
            if r == regions.len() {
                regions.push(Region {
                    bbox: self.boxes[label as usize],
                    samples: 0,
                });
            }
            let b = self.boxes[label as usize];
            let rb = &mut regions[r].bbox;
            *rb = [
                rb[0].min(b[0]),
                rb[1].min(b[1]),
                rb[2].max(b[2]),
                rb[3].max(b[3]),
            ];
            regions[r].samples += self.samples[label as usize];
            region_of.push(r as u32);
        }
        Regions { region_of, regions }
    }
}

/// A void region: its bounding box (x0, y0, x1, y1 inclusive) and its samples.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Region {
    pub bbox: [u32; 4],
    pub samples: u64,
}

/// The void regions of a raster, from a [`Labeler`] pass: the region of every provisional
/// label, in order of their first row.
#[derive(Debug, Clone, Default)]
pub struct Regions {
    region_of: Vec<u32>,
    pub regions: Vec<Region>,
}

impl Regions {
    /// The region of provisional `label`, as a replayed [`Labeler`] gives it.
    pub fn region_of(&self, label: u32) -> usize {
        self.region_of[label as usize] as usize
    }

    /// Region `r`'s window: its box grown by [`RIM`], clipped to `width x height`.
    fn window(&self, r: usize, width: u32, height: u32) -> [u32; 4] {
        let [x0, y0, x1, y1] = self.regions[r].bbox;
        [
            x0.saturating_sub(RIM),
            y0.saturating_sub(RIM),
            (x1 + RIM).min(width - 1),
            (y1 + RIM).min(height - 1),
        ]
    }

    pub fn samples(&self) -> usize {
        self.regions.iter().map(|r| r.samples as usize).sum()
    }
}

/// Where filled codes wait for the build: in memory (a raster read whole), or in an
/// anonymous temporary file (a streamed one: 4 bytes a void sample that memory need not
/// hold), each region's codes one after another.
#[derive(Debug)]
pub enum Store {
    Memory(Vec<i32>),
    File(std::fs::File),
}

impl Store {
    /// An anonymous temporary file, gone when dropped.
    pub fn file() -> std::io::Result<Store> {
        tempfile::tempfile().map(Store::File)
    }

    fn append(&mut self, codes: &[i32]) -> std::io::Result<()> {
        match self {
            Store::Memory(all) => all.extend_from_slice(codes),
            Store::File(file) => {
                use std::io::Write;
                let bytes: Vec<u8> = codes.iter().flat_map(|c| c.to_le_bytes()).collect();
                file.write_all(&bytes)?;
            }
        }
        Ok(())
    }

    /// `out.len()` codes from code `at`.
    fn read(&mut self, at: u64, out: &mut [i32]) -> std::io::Result<()> {
        match self {
            Store::Memory(all) => {
                let at = at as usize;
                let slice = all.get(at..at + out.len()).ok_or_else(|| {
                    std::io::Error::new(std::io::ErrorKind::UnexpectedEof, "fewer fills than voids")
                })?;
                out.copy_from_slice(slice);
            }
            Store::File(file) => {
                use std::io::{Read, Seek, SeekFrom};
                let mut bytes = vec![0u8; 4 * out.len()];
                file.seek(SeekFrom::Start(4 * at))?;
                file.read_exact(&mut bytes)?;
                for (o, b) in out.iter_mut().zip(bytes.chunks_exact(4)) {
                    *o = i32::from_le_bytes([b[0], b[1], b[2], b[3]]);
                }
            }
        }
        Ok(())
    }
}

/// The filled codes of every region, in the order its void samples come row by row.
#[derive(Debug)]
pub struct Fills {
    regions: Regions,
    store: Store,
    /// Per region, where its codes start in the store.
    starts: Vec<u64>,
    code_range: Option<(i32, i32)>,
    report: Option<FillReport>,
}

impl Fills {
    pub fn report(&self) -> Option<FillReport> {
        self.report.clone()
    }

    /// The smallest and largest filled code; `None` with nothing filled.
    pub fn code_range(&self) -> Option<(i32, i32)> {
        self.code_range
    }

    /// Puts the fills in place as the rows pass again, in order.
    pub fn stream(self) -> FillStream {
        let cursors = self.starts.clone();
        FillStream {
            labeler: Labeler::new(),
            fills: self,
            cursors,
            run: Vec::new(),
        }
    }
}

/// [`Fills`] put in place row by row, the rows labelled again as they pass.
#[derive(Debug)]
pub struct FillStream {
    labeler: Labeler,
    fills: Fills,
    /// Per region, where its next code is in the store.
    cursors: Vec<u64>,
    run: Vec<i32>,
}

impl FillStream {
    /// Fills the void samples of `codes` (the next row; `voids` marks them).
    pub fn apply(&mut self, codes: &mut [i32], voids: &[bool]) -> std::io::Result<()> {
        for run in self.labeler.push(voids) {
            let r = self.fills.regions.region_of(run.label);
            let (start, end) = (run.start as usize, run.end as usize);
            self.run.resize(end - start, 0);
            self.fills.store.read(self.cursors[r], &mut self.run)?;
            codes[start..end].copy_from_slice(&self.run);
            self.cursors[r] += (end - start) as u64;
        }
        Ok(())
    }
}

/// One region being solved: its window and, as the rows pass, its codes and classes.
#[derive(Debug)]
struct Window {
    region: usize,
    bbox: [u32; 4],
    codes: Vec<i32>,
    class: Vec<Class>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Class {
    Known,
    /// A void sample of the region being solved.
    Unknown,
    /// A void sample of another region: it takes no part.
    Other,
}

/// Solves every region of `regions` as the rows pass again (`next_row` gives each row's
/// codes and void flags, north first), holding only the windows the current row crosses,
/// and puts the filled codes in `store` (its errors made `E` by `io_error`).
pub fn solve<E>(
    regions: Regions,
    width: u32,
    height: u32,
    mut store: Store,
    io_error: impl Fn(std::io::Error) -> E,
    mut next_row: impl FnMut() -> Result<Option<(Vec<i32>, Vec<bool>)>, E>,
) -> Result<Fills, E> {
    let count = regions.regions.len();
    let mut by_start: Vec<usize> = (0..count).collect();
    by_start.sort_by_key(|&r| regions.window(r, width, height)[1]);
    let mut pending = by_start.into_iter().peekable();
    let mut open: Vec<Window> = Vec::new();
    // Regions are solved as their last row passes: their codes go to the store in that
    // order, and each region's start is kept.
    let mut starts = vec![0u64; count];
    let mut stored = 0u64;
    let mut code_range: Option<(i32, i32)> = None;
    let mut labeler = Labeler::new();
    let mut unconverged = 0;
    let mut region_row = vec![u32::MAX; width as usize];
    let mut y = 0u32;
    while let Some((codes, voids)) = next_row()? {
        for run in labeler.push(&voids) {
            let r = regions.region_of(run.label) as u32;
            region_row[run.start as usize..run.end as usize].fill(r);
        }
        while let Some(&r) = pending.peek() {
            let bbox = regions.window(r, width, height);
            if bbox[1] != y {
                break;
            }
            pending.next();
            open.push(Window {
                region: r,
                bbox,
                codes: Vec::new(),
                class: Vec::new(),
            });
        }
        for w in &mut open {
            let [x0, _, x1, _] = w.bbox;
            for x in x0..=x1 {
                let class = match region_row[x as usize] {
                    u32::MAX => Class::Known,
                    r if r as usize == w.region => Class::Unknown,
                    _ => Class::Other,
                };
                w.codes.push(codes[x as usize]);
                w.class.push(class);
            }
        }
        let (done, still): (Vec<Window>, Vec<Window>) = std::mem::take(&mut open)
            .into_iter()
            .partition(|w| w.bbox[3] == y);
        open = still;
        for w in done {
            let (filled, converged) = solve_window(&w);
            unconverged += usize::from(!converged);
            starts[w.region] = stored;
            stored += filled.len() as u64;
            for &c in &filled {
                code_range = Some(code_range.map_or((c, c), |(lo, hi)| (lo.min(c), hi.max(c))));
            }
            store.append(&filled).map_err(&io_error)?;
        }
        for run in labeler.above.iter() {
            region_row[run.start as usize..run.end as usize].fill(u32::MAX);
        }
        y += 1;
    }
    debug_assert!(y == height || count == 0, "{y} rows of {height}");
    let report = (count > 0).then(|| FillReport {
        samples: regions.samples(),
        regions: count,
        largest_region: regions
            .regions
            .iter()
            .map(|r| r.samples as usize)
            .max()
            .unwrap_or(0),
        unconverged,
    });
    Ok(Fills {
        regions,
        store,
        starts,
        code_range,
        report,
    })
}

/// Fills every `true` of `voids` in `codes` (row-major `width x height`), as a streamed
/// raster is filled. Returns `None` when there was nothing to fill. At least one sample must
/// be valid.
pub fn fill(codes: &mut [i32], voids: &[bool], width: usize, height: usize) -> Option<FillReport> {
    if voids.is_empty() || !voids.iter().any(|&v| v) || width == 0 {
        return None;
    }
    let mut labeler = Labeler::new();
    for row in voids.chunks(width) {
        labeler.push(row);
    }
    let regions = labeler.finish();
    // In memory, nothing here can fail: the store is a vector, as long as the voids.
    let fills = {
        let mut rows = codes.chunks(width).zip(voids.chunks(width));
        solve::<std::io::Error>(
            regions,
            width as u32,
            height as u32,
            Store::Memory(Vec::new()),
            |e| e,
            || Ok(rows.next().map(|(c, v)| (c.to_vec(), v.to_vec()))),
        )
        .ok()?
    };
    let report = fills.report();
    let mut stream = fills.stream();
    for (row, voids) in codes.chunks_mut(width).zip(voids.chunks(width)) {
        stream.apply(row, voids).ok()?;
    }
    report
}

/// The region's filled codes, row by row, and whether the membrane converged.
fn solve_window(w: &Window) -> (Vec<i32>, bool) {
    let width = (w.bbox[2] - w.bbox[0] + 1) as usize;
    let height = w.class.len() / width;
    let unknowns: Vec<usize> = (0..w.class.len())
        .filter(|&i| w.class[i] == Class::Unknown)
        .collect();
    let mut index = vec![usize::MAX; w.class.len()];
    for (k, &i) in unknowns.iter().enumerate() {
        index[i] = k;
    }
    let mut grid = Grid {
        width,
        height,
        class: &w.class,
        index: &index,
        known: w.codes.iter().map(|&c| f64::from(c)).collect(),
        equations: Vec::new(),
    };
    grid.equations = grid.equations();
    // The harmonic membrane first: a good start, and the answer where the thin plate has
    // too little rim to stand on.
    let start = vec![grid.rim_mean(&unknowns); unknowns.len()];
    let (harmonic, _) = conjugate_gradients(
        &|v, out| grid.laplacian_system(&unknowns, v, out),
        &grid.laplacian_rhs(&unknowns),
        start,
        64 * (width.max(height) + 1),
    );
    let limit = ITERATIONS_PER_SIDE_SQUARED * (width.max(height) + 1).pow(2);
    let (plate, converged) = conjugate_gradients(
        &|v, out| grid.plate_system(&unknowns, v, out),
        &grid.plate_rhs(&unknowns),
        harmonic.clone(),
        limit,
    );
    let solution = if plate.iter().all(|v| v.is_finite()) {
        plate
    } else {
        harmonic
    };
    let codes = solution
        .iter()
        .map(|&v| v.round().clamp(f64::from(i32::MIN), f64::from(i32::MAX)) as i32)
        .collect();
    (codes, converged)
}

/// A window's samples as the solver sees them.
struct Grid<'a> {
    width: usize,
    height: usize,
    class: &'a [Class],
    /// Per sample, its unknown's index (`usize::MAX` for a known or other one).
    index: &'a [usize],
    known: Vec<f64>,
    /// The cells of the thin plate's equations ([`Grid::equations`]).
    equations: Vec<usize>,
}

impl Grid<'_> {
    fn neighbours(&self, i: usize) -> impl Iterator<Item = usize> + '_ {
        let (x, y) = (i % self.width, i / self.width);
        [
            (x > 0).then(|| i - 1),
            (x + 1 < self.width).then(|| i + 1),
            (y > 0).then(|| i - self.width),
            (y + 1 < self.height).then(|| i + self.width),
        ]
        .into_iter()
        .flatten()
        .filter(|&j| self.class[j] != Class::Other)
    }

    /// The mean of the known samples next to the region.
    fn rim_mean(&self, unknowns: &[usize]) -> f64 {
        let (mut sum, mut n) = (0.0, 0.0);
        for &i in unknowns {
            for j in self.neighbours(i) {
                if self.class[j] == Class::Known {
                    sum += self.known[j];
                    n += 1.0;
                }
            }
        }
        if n > 0.0 { sum / n } else { 0.0 }
    }

    /// The harmonic system: at each unknown, its neighbours' count times it less their sum
    /// (neighbours past the raster's edge or in another region take no part), with the
    /// known neighbours moved to the right-hand side.
    fn laplacian_system(&self, unknowns: &[usize], v: &[f64], out: &mut [f64]) {
        for (k, &i) in unknowns.iter().enumerate() {
            let mut acc = 0.0;
            for j in self.neighbours(i) {
                acc += v[k];
                if self.class[j] == Class::Unknown {
                    acc -= v[self.index[j]];
                }
            }
            out[k] = acc;
        }
    }

    fn laplacian_rhs(&self, unknowns: &[usize]) -> Vec<f64> {
        unknowns
            .iter()
            .map(|&i| {
                self.neighbours(i)
                    .filter(|&j| self.class[j] == Class::Known)
                    .map(|j| self.known[j])
                    .sum()
            })
            .collect()
    }

    /// Cells whose Laplacian the thin plate minimises: every sample of the window, not of
    /// another region, whose stencil holds an unknown.
    fn equations(&self) -> Vec<usize> {
        (0..self.class.len())
            .filter(|&c| {
                self.class[c] != Class::Other
                    && (self.class[c] == Class::Unknown
                        || self.neighbours(c).any(|j| self.class[j] == Class::Unknown))
            })
            .collect()
    }

    /// The Laplacian at cell `c` of the heights `known` with the unknowns set to `v` (or
    /// to 0 where `with_known` is false, known ones too): its neighbours' count times it,
    /// less their sum. Past the raster's edge, or in another region, a neighbour is left
    /// out, as a free edge bends: without that an edge sample of a void along the raster's
    /// edge would be extrapolated from its neighbours' curvature (a 1,203-step spike on
    /// Mt Rainier's west edge).
    fn laplacian_at(&self, c: usize, v: &[f64], with_known: bool) -> f64 {
        let value = |j: usize| match self.class[j] {
            Class::Unknown => v[self.index[j]],
            Class::Known if with_known => self.known[j],
            _ => 0.0,
        };
        self.neighbours(c).map(|j| value(c) - value(j)).sum()
    }

    /// `L^T L v` over the unknowns: the thin plate's normal equations.
    fn plate_system(&self, _unknowns: &[usize], v: &[f64], out: &mut [f64]) {
        out.iter_mut().for_each(|o| *o = 0.0);
        for &c in &self.equations {
            let r = self.laplacian_at(c, v, false);
            self.scatter(c, r, out);
        }
    }

    /// `-L^T b`, `b` the Laplacians of the known samples alone.
    fn plate_rhs(&self, unknowns: &[usize]) -> Vec<f64> {
        let zero = vec![0.0; unknowns.len()];
        let mut out = vec![0.0; unknowns.len()];
        for &c in &self.equations {
            let b = self.laplacian_at(c, &zero, true);
            self.scatter(c, -b, &mut out);
        }
        out
    }

    /// Adds `r` times the stencil at `c` to `out` (`L^T` of one equation).
    fn scatter(&self, c: usize, r: f64, out: &mut [f64]) {
        let mut centre = 0.0;
        for j in self.neighbours(c) {
            centre += 1.0;
            if self.class[j] == Class::Unknown {
                out[self.index[j]] -= r;
            }
        }
        if self.class[c] == Class::Unknown {
            out[self.index[c]] += centre * r;
        }
    }
}

/// Conjugate gradients for `A x = b`, `A` symmetric positive (semi)definite given by
/// `apply`, from `x`, until no component of the residual passes [`TOLERANCE`] or after
/// `limit` iterations. Returns `x` and whether it converged.
fn conjugate_gradients(
    apply: &dyn Fn(&[f64], &mut [f64]),
    b: &[f64],
    mut x: Vec<f64>,
    limit: usize,
) -> (Vec<f64>, bool) {
    let n = b.len();
    if n == 0 {
        return (x, true);
    }
    let mut ax = vec![0.0; n];
    apply(&x, &mut ax);
    let mut r: Vec<f64> = b.iter().zip(&ax).map(|(b, a)| b - a).collect();
    let mut p = r.clone();
    let mut rr: f64 = r.iter().map(|v| v * v).sum();
    let mut ap = vec![0.0; n];
    for _ in 0..limit {
        if r.iter().all(|v| v.abs() <= TOLERANCE) {
            return (x, true);
        }
        apply(&p, &mut ap);
        let pap: f64 = p.iter().zip(&ap).map(|(p, a)| p * a).sum();
        if pap <= 0.0 || !pap.is_finite() {
            break;
        }
        let alpha = rr / pap;
        for k in 0..n {
            x[k] += alpha * p[k];
            r[k] -= alpha * ap[k];
        }
        let next: f64 = r.iter().map(|v| v * v).sum();
        let beta = next / rr;
        rr = next;
        for k in 0..n {
            p[k] = r[k] + beta * p[k];
        }
    }
    let converged = r.iter().all(|v| v.abs() <= TOLERANCE);
    (x, converged)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A `width x height` raster of `surface(x, y)` (code steps), with the samples where
    /// `hole(x, y)` holds made voids (-32768).
    fn punched(
        width: usize,
        height: usize,
        surface: impl Fn(f64, f64) -> f64,
        hole: impl Fn(usize, usize) -> bool,
    ) -> (Vec<i32>, Vec<i32>, Vec<bool>) {
        let mut truth = Vec::new();
        let mut voids = Vec::new();
        for y in 0..height {
            for x in 0..width {
                truth.push(surface(x as f64, y as f64).round() as i32);
                voids.push(hole(x, y));
            }
        }
        let codes = truth
            .iter()
            .zip(&voids)
            .map(|(&t, &v)| if v { -32768 } else { t })
            .collect();
        (truth, codes, voids)
    }

    fn worst(a: &[i32], b: &[i32]) -> i32 {
        a.iter()
            .zip(b)
            .map(|(a, b)| (a - b).abs())
            .max()
            .unwrap_or(0)
    }

    #[test]
    fn a_plane_and_a_paraboloid_come_back_through_their_holes() {
        let disc = |cx: f64, cy: f64, r: f64| {
            move |x: usize, y: usize| (x as f64 - cx).hypot(y as f64 - cy) <= r
        };
        let two_holes =
            |x: usize, y: usize| disc(20.0, 18.0, 9.0)(x, y) || disc(45.0, 40.0, 5.0)(x, y);
        // A plane (12 code steps a sample east, 7 south) and a paraboloid with 3,000 code
        // steps between its middle and its corners.
        let plane = |x: f64, y: f64| 100.0 + 12.0 * x - 7.0 * y;
        let bowl = |x: f64, y: f64| 0.6 * ((x - 30.0).powi(2) + (y - 25.0).powi(2));
        for (name, surface) in [
            ("plane", &plane as &dyn Fn(f64, f64) -> f64),
            ("paraboloid", &bowl),
        ] {
            let (truth, mut codes, voids) = punched(64, 56, surface, two_holes);
            let report = fill(&mut codes, &voids, 64, 56).expect("voids");
            assert_eq!(report.regions, 2, "{name}");
            assert_eq!(report.unconverged, 0, "{name}");
            // Within a code step (the known samples are rounded to whole steps).
            assert!(
                worst(&truth, &codes) <= 1,
                "{name}: off by {}",
                worst(&truth, &codes)
            );
        }
    }

    #[test]
    fn fronts_from_different_rims_meet_without_a_step() {
        // A long void across a valley, 1,000 steps deep on one side and 5,000 on the other:
        // the wave fill met in a flat step; the membrane is smooth, every jump between
        // neighbours inside it within the largest jump of the terrain around it.
        let surface = |x: f64, y: f64| 1000.0 + 60.0 * x + 10.0 * (y / 3.0).sin() * y;
        let hole = |x: usize, y: usize| (10..54).contains(&x) && (20..30).contains(&y);
        let (truth, mut codes, voids) = punched(64, 48, surface, hole);
        fill(&mut codes, &voids, 64, 48).expect("voids");
        // Every pair of 4-neighbours, east and south.
        let jump = |c: &[i32], inside: bool| {
            let mut most = 0;
            for y in 0..48 {
                for x in 0..64 {
                    let i = y * 64 + x;
                    for j in [(x + 1 < 64).then(|| i + 1), (y + 1 < 48).then(|| i + 64)]
                        .into_iter()
                        .flatten()
                    {
                        if (voids[i] || voids[j]) == inside {
                            most = most.max((c[i] - c[j]).abs());
                        }
                    }
                }
            }
            most
        };
        assert!(
            jump(&codes, true) <= jump(&truth, false),
            "{} > {}",
            jump(&codes, true),
            jump(&truth, false)
        );
        // Nor does it invent heights: every filled sample within the known samples' range.
        let known = || {
            codes
                .iter()
                .zip(&voids)
                .filter(|(_, v)| !**v)
                .map(|(c, _)| *c)
        };
        let (low, high) = (known().min().unwrap_or(0), known().max().unwrap_or(0));
        assert!(
            codes.iter().all(|&c| (low..=high).contains(&c)),
            "{:?} outside {low}..={high}",
            (codes.iter().min(), codes.iter().max())
        );
    }

    #[test]
    fn regions_are_found_as_the_rows_pass_and_again_the_same_way() {
        // A U whose arms meet two rows down, a lone sample, and a diagonal pair.
        let rows = ["#..#....#", "#..#.....", "####...#.", "........#"];
        let voids: Vec<Vec<bool>> = rows
            .iter()
            .map(|r| r.chars().map(|c| c == '#').collect())
            .collect();
        let mut labeler = Labeler::new();
        let first: Vec<Vec<Run>> = voids.iter().map(|r| labeler.push(r)).collect();
        let regions = labeler.finish();
        assert_eq!(regions.regions.len(), 3);
        let mut again = Labeler::new();
        let second: Vec<Vec<Run>> = voids.iter().map(|r| again.push(r)).collect();
        assert_eq!(first, second, "labelling is deterministic");
        let region = |y: usize, k: usize| regions.region_of(first[y][k].label);
        // Both arms of the U are one region, though they met only on its third row.
        assert_eq!(region(0, 0), region(0, 1));
        assert_eq!(region(0, 0), region(2, 0));
        assert_eq!(regions.regions[region(0, 0)].samples, 8);
        assert_eq!(regions.regions[region(0, 0)].bbox, [0, 0, 3, 2]);
        // The diagonal pair is 8-connected.
        assert_eq!(region(2, 1), region(3, 0));
        assert_eq!(regions.regions[region(2, 1)].samples, 2);
        assert_eq!(regions.samples(), 11);
    }

    #[test]
    fn a_raster_filled_as_its_rows_pass_matches_one_filled_whole() {
        let surface = |x: f64, y: f64| 500.0 + 30.0 * (x / 7.0).sin() * (y / 5.0).cos() * x;
        let hole = |x: usize, y: usize| {
            (x * 7 + y * 13).is_multiple_of(29) || ((5..9).contains(&x) && (3..40).contains(&y))
        };
        let (_, codes, voids) = punched(40, 44, surface, hole);
        let mut whole = codes.clone();
        let report = fill(&mut whole, &voids, 40, 44).expect("voids");
        // Streamed: regions from one pass, solved in a second, put in place in a third.
        let mut labeler = Labeler::new();
        for row in voids.chunks(40) {
            labeler.push(row);
        }
        let mut rows = codes.chunks(40).zip(voids.chunks(40));
        let store = Store::file().expect("a temporary file");
        let fills = solve::<std::io::Error>(
            labeler.finish(),
            40,
            44,
            store,
            |e| e,
            || Ok(rows.next().map(|(c, v)| (c.to_vec(), v.to_vec()))),
        )
        .expect("solved");
        assert_eq!(fills.report(), Some(report));
        let mut stream = fills.stream();
        let mut streamed = codes.clone();
        for (row, v) in streamed.chunks_mut(40).zip(voids.chunks(40)) {
            stream.apply(row, v).expect("read back");
        }
        assert_eq!(streamed, whole);
        assert!(whole.iter().all(|&c| c != -32768));
    }

    #[test]
    fn a_single_void_on_a_slope_takes_the_slope_and_nothing_to_fill_reports_nothing() {
        // A slope of 3 steps east and 5 south, its middle sample missing, in a raster so
        // small that every other sample is on its edge.
        let mut codes = vec![0, 3, 6, 5, -32768, 11, 10, 13, 16];
        let voids: Vec<bool> = codes.iter().map(|&c| c == -32768).collect();
        let report = fill(&mut codes, &voids, 3, 3).expect("a void");
        assert_eq!(
            (report.samples, report.regions, report.largest_region),
            (1, 1, 1)
        );
        assert_eq!(codes[4], 8);
        assert_eq!(fill(&mut [1, 2], &[], 2, 1), None);
        assert_eq!(fill(&mut [1, 2], &[false, false], 2, 1), None);
    }
}
