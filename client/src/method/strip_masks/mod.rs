//! Strip masks (Pouderoux and Marvie 2005): per frame, culling, importance, the global
//! triangle budget shared greedily ([`crate::lod`]), one precomputed strip per mask level
//! shared by every tile (section 5.1), cracks filled by a [`CrackFiller`] (section 5.4).
//! As the reference of the accuracy measures it ignores the budget and draws every visible
//! tile at mask 0, with no filler.

use super::fillers::{self, Across, CrackFiller};
use super::{LodMethod, MethodBytes, MethodConfig, MethodInput, MethodKind, MethodOutput};
use crate::lod::plan::{self, Candidate, LodSettings};
use crate::lod::strips::MaskSet;
use crate::render::{Frame, IndexSet, TileExtras};
use std::collections::HashMap;
use std::sync::Arc;
use terrain_shared::{TileId, mask};
use web_time::Instant;

/// The strip-mask method. See the module documentation.
#[derive(Debug)]
pub struct StripMasks {
    lod: LodSettings,
    filler: CrackFiller,
    masks: Arc<MaskSet>,
    reference: bool,
    /// One index set per mask level drawn so far, shared by every tile.
    strips: HashMap<u32, IndexSet>,
    /// The skirts of each mask level drawn with skirts so far.
    skirts: HashMap<u32, IndexSet>,
    /// The planar shadow's bands ([`fillers::band_strip`]) by mask level and what each side
    /// faces, and the crack probe's (bands unprojected, down to the skirts' bottom) by mask
    /// level and shared sides, made as frames need them.
    bands: HashMap<BandKey, (IndexSet, u64)>,
    probes: HashMap<ProbeKey, (IndexSet, u64)>,
    /// The paper's planar shadow's four corners (`terrain_shaders::shadow_base`), made when
    /// first drawn.
    quad: Option<IndexSet>,
    /// Frames drawn, and the last frame each mask level was drawn in: a level's strip and
    /// skirts unused for [`KEEP_UNUSED_FRAMES`] are dropped; so is any band or probe (each
    /// with the frame it was last drawn in).
    frame: u64,
    last_used: HashMap<u32, u64>,
    /// [`LodMethod::reserved_bytes`], worked out when configured.
    reserved: u64,
}

/// Frames an index set is kept after it (or its level) was last drawn.
pub const KEEP_UNUSED_FRAMES: u64 = 30;

impl StripMasks {
    /// The method for tiles of `tile_size` samples a side (it makes its GPU index sets as
    /// frames need them).
    pub fn new(config: &MethodConfig, tile_size: u32) -> StripMasks {
        let mut method = StripMasks {
            lod: config.lod,
            filler: config.filler,
            masks: Arc::new(MaskSet::new(tile_size)),
            reference: config.kind == MethodKind::Reference,
            strips: HashMap::new(),
            skirts: HashMap::new(),
            bands: HashMap::new(),
            probes: HashMap::new(),
            quad: None,
            frame: 0,
            last_used: HashMap::new(),
            reserved: 0,
        };
        method.configure(config);
        method
    }

    /// [`LodMethod::reserved_bytes`] for the configured filler: the coarsest level's strip
    /// (and skirts), or the paper's quad, with which every tile can be drawn; finer strips,
    /// skirts and bands are made when the limit has room for them.
    fn compute_reserved(&self) -> u64 {
        let n = self.masks.tile_size();
        let coarsest = self.masks.coarsest_level();
        let index_bytes = |indices: usize| 4 * (indices as u64).max(1);
        let filler = match self.filler {
            _ if self.reference => 0,
            CrackFiller::Skirts => index_bytes(fillers::skirt_strip(n, coarsest).len()),
            CrackFiller::PlanarShadowPaper => index_bytes(4),
            CrackFiller::None | CrackFiller::PlanarShadow | CrackFiller::CrackProbe => 0,
        };
        let strip = if self.reference { 0 } else { coarsest };
        self.masks.bytes() + 4 * self.masks.strip_len(strip) as u64 + filler
    }

    /// What tile `id`, drawn at mask `level`, gives the shader this frame: the plane below it
    /// (the skirts' bottom, the crack probe's too) and, for the paper's planar shadow, its
    /// corners projected onto that plane; for the banded planar shadow, what each side faces
    /// (`terrain.wgsl`, `shadow_band`).
    fn extras(
        frame: &Frame<'_>,
        layout: &plan::Layout,
        filler: CrackFiller,
        (id, level): (TileId, u32),
        min_m: f64,
        sides: &Sides,
    ) -> TileExtras {
        // The plane's depth is a tenth of a level-0 tile's side at every level: a coarser
        // tile spans more, but the cracks along its sides are no deeper for it.
        let floor = min_m - fillers::filler_depth_m(layout.tile_extent_m());
        let extent = layout.tile_extent_m_at(id.level);
        let mut extras = TileExtras {
            floor_m: floor as f32,
            ..TileExtras::default()
        };
        if filler == CrackFiller::PlanarShadow {
            for (side, band) in sides.band.iter().enumerate() {
                let (across, plane) = match band {
                    Some(Band::Mask(theirs)) => (*theirs as f32, floor),
                    Some(Band::Seam { depth }) => (-1.0, *depth),
                    None => (-1.0, floor),
                };
                extras.points[0][side] = plane as f32;
                extras.points[1][side] = across;
            }
            extras.points[2][0] = level as f32;
            return extras;
        }
        if filler == CrackFiller::CrackProbe {
            // The probe: every shared side, down to the skirts' bottom (`shadow_band`).
            extras.points[1] = [-1.0; 4];
            extras.points[2] = [level as f32, 1.0, 0.0, 0.0];
            return extras;
        }
        if filler != CrackFiller::PlanarShadowPaper {
            return extras;
        }
        let Some(heights) = frame.tiles().heights(id) else {
            return extras;
        };
        let eye = frame.camera().position;
        let last = layout.tile_size as usize - 1;
        let [x0, y0] = layout.tile_origin_m(id);
        let plane = floor - eye[2];
        for (k, corner) in extras.points.iter_mut().enumerate() {
            // North-west, south-west, north-east, south-east.
            let (column, row) = ((k / 2) * last, (k % 2) * last);
            let height = f64::from(heights.metres(column, row) as f32);
            let p = fillers::shadow_corner(
                glam::DVec3::new(
                    x0 + (k / 2) as f64 * extent[0] - eye[0],
                    height - eye[2],
                    y0 + (k % 2) as f64 * extent[1] - eye[1],
                ),
                plane,
            );
            *corner = [p.x as f32, p.y as f32, p.z as f32, 1.0];
        }
        extras
    }

    /// Draws `draws` (resident tiles of `tiles` at their mask levels) into `frame`, cracks
    /// filled by `filler`: the drawing half of [`LodMethod::draw`], for a plan made
    /// elsewhere.
    pub fn draw_levels(
        &mut self,
        frame: &mut Frame<'_>,
        layout: &plan::Layout,
        tiles: &[Candidate<'_>],
        draws: &mut [plan::Draw],
        filler: CrackFiller,
        mut room: u64,
    ) -> u32 {
        let gpu = frame.gpu().clone();
        let n = self.masks.tile_size();
        self.frame += 1;
        let now = self.frame;
        // The level whose strip the reservation holds: every tile can be drawn with it.
        let coarsest = if self.reference {
            0
        } else {
            self.masks.coarsest_level()
        };
        let mut degraded = 0;
        // The strips first: a level whose strip the limit has no room for is drawn with the
        // finest strip held that is coarser, or the coarsest (which the reservation holds).
        for d in draws.iter_mut() {
            if !self.strips.contains_key(&d.level) {
                let bytes = 4 * self.masks.strip_len(d.level) as u64;
                if d.level != coarsest && !self.make_room(&mut room, bytes) {
                    let held = self
                        .strips
                        .keys()
                        .copied()
                        .filter(|&l| l > d.level)
                        .min()
                        .unwrap_or(coarsest);
                    d.level = held;
                    degraded += 1;
                }
                let masks = &self.masks;
                self.strips.entry(d.level).or_insert_with(|| {
                    IndexSet::new(&gpu, &masks.build(d.level), masks.triangle_count(d.level))
                });
            }
            self.last_used.insert(d.level, now);
        }
        self.last_used
            .retain(|_, &mut used| now - used <= KEEP_UNUSED_FRAMES);
        let used = &self.last_used;
        self.strips.retain(|level, _| used.contains_key(level));
        self.skirts.retain(|level, _| used.contains_key(level));
        self.bands
            .retain(|_, (_, last)| now - *last <= KEEP_UNUSED_FRAMES);
        self.probes
            .retain(|_, (_, last)| now - *last <= KEEP_UNUSED_FRAMES);
        let draws: &[plan::Draw] = draws;
        let sides = match filler {
            CrackFiller::PlanarShadow | CrackFiller::CrackProbe => {
                sides_of(frame, layout, tiles, draws)
            }
            _ => vec![Sides::default(); draws.len()],
        };
        // Per draw, the filler's index set, if it draws one: the bands' or the probe's key.
        // A filler set the limit has no room for is left out (its cracks may show).
        let mut band_key = vec![None; draws.len()];
        let mut probe_key = vec![None; draws.len()];
        let mut skirted = vec![false; draws.len()];
        for (k, d) in draws.iter().enumerate() {
            match filler {
                CrackFiller::Skirts => {
                    if !self.skirts.contains_key(&d.level) {
                        let strip = fillers::skirt_strip(n, d.level);
                        if d.level != coarsest
                            && !self.make_room(&mut room, 4 * (strip.len() as u64).max(1))
                        {
                            degraded += 1;
                            continue;
                        }
                        self.skirts.insert(
                            d.level,
                            IndexSet::new(&gpu, &strip, fillers::skirt_triangles(n, d.level)),
                        );
                    }
                    skirted[k] = true;
                }
                CrackFiller::PlanarShadow => {
                    let across = sides[k].band.map(|b| b.map(Band::across));
                    if across.iter().any(Option::is_some) {
                        let key = (d.level, across);
                        if !self.bands.contains_key(&key) {
                            let strip = fillers::band_strip(n, d.level, across);
                            if !self.make_room(&mut room, 4 * (strip.len() as u64).max(1)) {
                                degraded += 1;
                                continue;
                            }
                            let set = IndexSet::new(
                                &gpu,
                                &strip,
                                fillers::band_triangles(n, d.level, across),
                            );
                            self.bands.insert(key, (set, now));
                        }
                        if let Some((_, last)) = self.bands.get_mut(&key) {
                            *last = now;
                        }
                        band_key[k] = Some(key);
                    }
                }
                CrackFiller::CrackProbe => {
                    let on = sides[k].shared;
                    if on.iter().any(|&on| on) {
                        // Along the tile's own polyline, whatever lies across.
                        let along = on.map(|on| on.then_some(Across::Seam));
                        let key = (d.level, on);
                        if !self.probes.contains_key(&key) {
                            let strip = fillers::band_strip(n, d.level, along);
                            if !self.make_room(&mut room, 4 * (strip.len() as u64).max(1)) {
                                degraded += 1;
                                continue;
                            }
                            let set = IndexSet::new(
                                &gpu,
                                &strip,
                                fillers::band_triangles(n, d.level, along),
                            );
                            self.probes.insert(key, (set, now));
                        }
                        if let Some((_, last)) = self.probes.get_mut(&key) {
                            *last = now;
                        }
                        probe_key[k] = Some(key);
                    }
                }
                CrackFiller::None | CrackFiller::PlanarShadowPaper => {}
            }
        }
        if filler == CrackFiller::PlanarShadowPaper && self.quad.is_none() {
            let corner = terrain_shaders::shadow_base(n);
            self.quad = Some(IndexSet::new(
                &gpu,
                &[corner, corner + 1, corner + 2, corner + 3],
                2,
            ));
        }
        let min_m: HashMap<TileId, f64> = tiles.iter().map(|t| (t.id, t.min_m)).collect();
        let tiles: Vec<(TileId, TileExtras)> = draws
            .iter()
            .zip(&sides)
            .map(|(d, sides)| {
                let min_m = min_m.get(&d.id).copied().unwrap_or(0.0);
                (
                    d.id,
                    Self::extras(frame, layout, filler, (d.id, d.level), min_m, sides),
                )
            })
            .collect();
        let slots = frame.prepare_tiles(&tiles);
        let mut level_of = vec![0; tiles.len()];
        let mut skirted_of = vec![false; tiles.len()];
        // Per slot, what is drawn after every surface: the tile's bands or its probe.
        let mut late_of: Vec<Option<&IndexSet>> = vec![None; tiles.len()];
        for (k, (d, slot)) in draws.iter().zip(&slots).enumerate() {
            if let Some(slot) = *slot {
                level_of[slot] = d.level;
                skirted_of[slot] = skirted[k];
                late_of[slot] = match (band_key[k], probe_key[k]) {
                    (Some(key), _) => Some(&self.bands[&key].0),
                    (None, Some(key)) => Some(&self.probes[&key].0),
                    (None, None) => None,
                };
            }
        }
        let order = frame.draw_order();
        let mut pass = frame.last_pass();
        for &slot in &order {
            let level = level_of[slot];
            pass.bind_tile(slot);
            let strip = &self.strips[&level];
            pass.draw(strip);
            pass.stats_mut().triangles += u64::from(strip.triangles);
            if filler == CrackFiller::Skirts
                && skirted_of[slot]
                && let Some(skirt) = self.skirts.get(&level)
            {
                pass.draw(skirt);
                pass.stats_mut().filler_triangles += u64::from(skirt.triangles);
            }
        }
        match (filler, &self.quad) {
            (CrackFiller::PlanarShadow | CrackFiller::CrackProbe, _) => {
                // After every surface, so that the early depth test rejects the bands the
                // surfaces in front hide. A band hangs from a shared side, so it is clipped
                // at the terrain's edge only with tiles that reach past it (padded).
                for &slot in &order {
                    if let Some(set) = late_of[slot] {
                        pass.bind_tile(slot);
                        pass.draw(set);
                        pass.stats_mut().filler_triangles += u64::from(set.triangles);
                    }
                }
            }
            (CrackFiller::PlanarShadowPaper, Some(quad)) => {
                // After every surface, so the depth test hides the shadows where tiles
                // cover them. A shadow reaches past its tile, so past the terrain's edge too.
                pass.clip_everything();
                for &slot in &order {
                    pass.bind_tile(slot);
                    pass.draw(quad);
                    pass.stats_mut().filler_triangles += u64::from(quad.triangles);
                }
            }
            _ => {}
        }
        drop(pass);
        frame.stats_mut().degraded_draws += degraded;
        degraded
    }

    /// Takes `bytes` out of `room` for an index set about to be made, dropping sets the
    /// frame does not use to make it if need be; `false` (nothing taken) when even that
    /// leaves too little.
    fn make_room(&mut self, room: &mut u64, bytes: u64) -> bool {
        if *room < bytes {
            *room += self.trim(bytes - *room);
        }
        if *room < bytes {
            return false;
        }
        *room -= bytes;
        true
    }
}

/// A tile's bands: its mask level and what each side faces.
type BandKey = (u32, [Option<Across>; 4]);
/// A tile's crack probe: its mask level and which sides are shared.
type ProbeKey = (u32, [bool; 4]);

/// An index set [`LodMethod::trim`] may drop.
#[derive(Debug, Clone, Copy)]
enum Stale {
    Band(BandKey),
    Probe(ProbeKey),
    Level(u32),
}

/// What lies across each side (north, east, south, west) of a drawn tile this frame.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Sides {
    /// A drawn tile: the side is shared (the crack probe's skirts hang there).
    pub shared: [bool; 4],
    /// Where a crack can open, the planar shadow's band. `None` where none can: no
    /// neighbour drawn (the terrain's border, or a tile not drawn), or one of the same level
    /// drawing the side through the same samples.
    pub band: [Option<Band>; 4],
}

/// The planar shadow's band along a side where a crack can open.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Band {
    /// A tile of the same pyramid level drawn at this mask: the crack lies between the two
    /// polylines through the shared samples, so its bottom at each sample is the lower of
    /// the two there, which the shader computes (`terrain.wgsl`, `shadow_band`).
    Mask(u32),
    /// A seam: tiles of another pyramid level, sampled on another grid. The crack lies
    /// between this tile's polyline and theirs, so it reaches no lower than this tile's
    /// polyline less the largest gap between the two along the side ([`seam_depth`]): the
    /// band's plane at each sample, that far below it.
    Seam { depth: f64 },
}

impl Band {
    /// What the side faces, for the band's index set.
    pub fn across(self) -> Across {
        match self {
            Band::Mask(theirs) => Across::Mask(theirs),
            Band::Seam { .. } => Across::Seam,
        }
    }
}

/// [`Sides`] of every draw of `draws` (mask levels of `tiles`, resident in `frame`).
pub fn sides_of(
    frame: &Frame<'_>,
    layout: &plan::Layout,
    tiles: &[Candidate<'_>],
    draws: &[plan::Draw],
) -> Vec<Sides> {
    let level_of: HashMap<TileId, u32> = draws.iter().map(|d| (d.id, d.level)).collect();
    let candidate: HashMap<TileId, &Candidate<'_>> = tiles.iter().map(|t| (t.id, t)).collect();
    let n = layout.tile_size;
    draws
        .iter()
        .map(|d| {
            let mut sides = Sides::default();
            if !candidate.contains_key(&d.id) || frame.tiles().heights(d.id).is_none() {
                return sides;
            }
            for (side, (dx, dy)) in [(0i64, -1i64), (1, 0), (0, 1), (-1, 0)]
                .into_iter()
                .enumerate()
            {
                let next = (
                    u32::try_from(i64::from(d.id.x) + dx),
                    u32::try_from(i64::from(d.id.y) + dy),
                );
                let neighbour = match next {
                    (Ok(x), Ok(y)) => level_of.get(&TileId::at(d.id.level, x, y)).copied(),
                    _ => None,
                };
                if let Some(theirs) = neighbour {
                    sides.shared[side] = true;
                    if fillers::masks_differ(n, d.level, theirs) {
                        sides.band[side] = Some(Band::Mask(theirs));
                    }
                } else if candidate[&d.id].seams[side]
                    && let Some(depth) = seam_depth(frame, layout, draws, d, side)
                {
                    sides.shared[side] = true;
                    sides.band[side] = Some(Band::Seam { depth });
                }
            }
            sides
        })
        .collect()
}

/// The deepest crack side `side` of `draw` can open against the drawn tiles of other
/// pyramid levels across it (a seam): the largest vertical gap, within the side's span,
/// between this tile's polyline and theirs (each through the border samples its mask keeps).
/// Both are linear between their vertices, so the gap is largest at a vertex of either or at
/// an end of a neighbour's span. `None` when no such tile is drawn with its samples
/// resident.
pub fn seam_depth(
    frame: &Frame<'_>,
    layout: &plan::Layout,
    draws: &[plan::Draw],
    draw: &plan::Draw,
    side: usize,
) -> Option<f64> {
    let n = layout.tile_size;
    // Side `side` of a tile as (the coordinate across it, the span along it), in metres.
    let line = |id: TileId, side: usize| {
        let [x0, y0] = layout.tile_origin_m(id);
        let [ex, ey] = layout.tile_extent_m_at(id.level);
        match side {
            0 => (y0, x0, x0 + ex),
            1 => (x0 + ex, y0, y0 + ey),
            2 => (y0 + ey, x0, x0 + ex),
            _ => (x0, y0, y0 + ey),
        }
    };
    // The polyline `id` draws along its side `side`: (position along it, metres).
    let polyline = |id: TileId, level: u32, side: usize| -> Option<Vec<(f64, f64)>> {
        let heights = frame.tiles().heights(id)?;
        let (_, start, end) = line(id, side);
        let step = (end - start) / f64::from(n - 1);
        Some(
            mask::kept_indices(n, level)
                .into_iter()
                .map(|k| {
                    let (column, row) = fillers::side_sample(n, side, k);
                    (
                        start + f64::from(k) * step,
                        heights.metres(column as usize, row as usize),
                    )
                })
                .collect(),
        )
    };
    let at = |line: &[(f64, f64)], x: f64| -> f64 {
        let k = line.partition_point(|v| v.0 < x).clamp(1, line.len() - 1);
        let ((a, ha), (b, hb)) = (line[k - 1], line[k]);
        ha + (hb - ha) * ((x - a) / (b - a)).clamp(0.0, 1.0)
    };
    let (across, from, to) = line(draw.id, side);
    let tolerance = 1e-6 * (to - from);
    let ours = polyline(draw.id, draw.level, side)?;
    let mut depth: Option<f64> = None;
    for other in draws.iter().filter(|o| o.id.level != draw.id.level) {
        let (their_across, their_from, their_to) = line(other.id, (side + 2) % 4);
        if (their_across - across).abs() > tolerance
            || their_to <= from + tolerance
            || their_from >= to - tolerance
        {
            continue;
        }
        let Some(theirs) = polyline(other.id, other.level, (side + 2) % 4) else {
            continue;
        };
        let (lo, hi) = (from.max(their_from), to.min(their_to));
        let gap = ours
            .iter()
            .chain(&theirs)
            .map(|v| v.0)
            .filter(|&x| x > lo && x < hi)
            .chain([lo, hi])
            .map(|x| (at(&ours, x) - at(&theirs, x)).abs())
            .fold(0.0, f64::max);
        depth = Some(depth.unwrap_or(0.0).max(gap));
    }
    depth
}

impl LodMethod for StripMasks {
    fn full_resolution_only(&self) -> bool {
        self.reference
    }

    fn name(&self) -> String {
        if self.reference {
            MethodKind::Reference.name().to_string()
        } else {
            MethodKind::StripMasks.name_with(self.filler)
        }
    }

    fn configure(&mut self, config: &MethodConfig) {
        if self.reference {
            // The reference keeps full resolution: no cap, no filler.
            self.lod = LodSettings {
                cap_at_needed: false,
                ..config.lod
            };
            self.filler = CrackFiller::None;
        } else {
            self.lod = config.lod;
            self.filler = config.filler;
        }
        self.reserved = self.compute_reserved();
    }

    fn uses_budget(&self) -> bool {
        !self.reference
    }

    fn draw(&mut self, input: &MethodInput<'_>, frame: &mut Frame<'_>) -> MethodOutput {
        let started = Instant::now();
        let budget = if self.reference {
            u32::MAX
        } else {
            input.budget
        };
        let mut plan = plan::plan_frame(
            frame.camera(),
            frame.viewport(),
            input.layout,
            input.tiles,
            budget,
            &self.masks,
            &self.lod,
        );
        if self.reference {
            // Full resolution whatever the importances made of the budget.
            for d in &mut plan.draws {
                d.level = 0;
            }
            plan.triangles = plan.draws.len() as u64 * u64::from(self.masks.triangle_count(0));
        }
        let lod_ms = started.elapsed().as_secs_f64() * 1e3;

        let degraded = self.draw_levels(
            frame,
            input.layout,
            input.tiles,
            &mut plan.draws,
            self.filler,
            input.room,
        );
        if degraded > 0 {
            plan.triangles = plan
                .draws
                .iter()
                .map(|d| u64::from(self.masks.triangle_count(d.level)))
                .sum();
        }
        MethodOutput::of_plan(plan, lod_ms)
    }

    fn shared_bytes(&self) -> MethodBytes {
        MethodBytes {
            cpu: self.masks.bytes(),
            gpu: self
                .strips
                .values()
                .chain(self.skirts.values())
                .chain(self.bands.values().map(|(set, _)| set))
                .chain(self.probes.values().map(|(set, _)| set))
                .chain(&self.quad)
                .map(IndexSet::bytes)
                .sum(),
        }
    }

    /// The coarsest strip (the reference's: level 0, which it draws every tile with) and its
    /// filler's: what every frame can be drawn with.
    fn reserved_bytes(&self, _viewport: [u32; 2]) -> u64 {
        self.reserved
    }

    /// Bands and probes the last frame did not draw, least recently drawn first; then the
    /// strips and skirts of levels it did not draw.
    fn trim(&mut self, bytes: u64) -> u64 {
        let now = self.frame;
        let mut stale: Vec<(u64, Stale)> = self
            .bands
            .iter()
            .filter(|(_, (_, last))| *last < now)
            .map(|(key, (_, last))| (*last, Stale::Band(*key)))
            .chain(
                self.probes
                    .iter()
                    .filter(|(_, (_, last))| *last < now)
                    .map(|(key, (_, last))| (*last, Stale::Probe(*key))),
            )
            .collect();
        stale.sort_by_key(|(last, _)| *last);
        let mut levels: Vec<(u64, u32)> = self
            .last_used
            .iter()
            .filter(|(_, last)| **last < now)
            .map(|(level, last)| (*last, *level))
            .collect();
        levels.sort_unstable();
        stale.extend(
            levels
                .into_iter()
                .map(|(last, level)| (last, Stale::Level(level))),
        );
        let mut freed = 0;
        for (_, item) in stale {
            if freed >= bytes {
                break;
            }
            freed += match item {
                Stale::Band(key) => self.bands.remove(&key).map_or(0, |(set, _)| set.bytes()),
                Stale::Probe(key) => self.probes.remove(&key).map_or(0, |(set, _)| set.bytes()),
                Stale::Level(level) => {
                    self.last_used.remove(&level);
                    self.strips.remove(&level).map_or(0, |set| set.bytes())
                        + self.skirts.remove(&level).map_or(0, |set| set.bytes())
                }
            };
        }
        freed
    }
}
