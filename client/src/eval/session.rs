//! A measuring session: a scene streamed from a server and rendered offscreen, whose
//! frames can be drawn with any method and measured against the reference at the same
//! camera. The accuracy sweep and the stability matrix both run on it.

use super::frame::{Capture, FrameMeasures, Unfilled, measure};
use crate::flight::FlightError;
use crate::lod::budget::BudgetMode;
use crate::method::CrackFiller;
use crate::method::MethodKind;
use crate::render::{Camera, Gpu, Offscreen};
use crate::requests::{Fetcher, FetcherConfig};
use crate::scene::{DrawReport, RenderConfig, Scene, Update, expected_tile_bytes};
use std::sync::Arc;
use std::time::{Duration, Instant};
use terrain_shared::Manifest;

/// A scene, its fetcher and an offscreen target. See the module documentation.
#[derive(Debug)]
pub struct Session {
    pub manifest: Arc<Manifest>,
    pub scene: Scene,
    pub fetcher: Fetcher,
    pub gpu: Gpu,
    pub target: Offscreen,
    pub config: RenderConfig,
    frame: u64,
    /// The last captured frame's method measures.
    method_measures: Vec<(&'static str, f64)>,
}

/// One frame drawn and measured against its reference.
#[derive(Debug, Clone)]
pub struct Measured {
    pub measures: FrameMeasures,
    pub report: DrawReport,
    /// Median of the timed draws, milliseconds (plan, render and the GPU's completion).
    pub frame_ms: f64,
    /// Median GPU time of the render pass, where the adapter has timestamps.
    pub gpu_ms: Option<f64>,
    pub capture: Capture,
    /// What the scene held right after the frame: CPU bytes plus the GPU allocations made
    /// for the terrain ([`Scene::cpu_bytes`] + [`Scene::gpu_bytes`]).
    pub held_bytes: u64,
    /// Measures only the method knows, read back after the frame
    /// ([`crate::method::LodMethod::frame_measures`]: the projective grid's shares of
    /// pixels past the threshold and ray cast).
    pub method_measures: Vec<(&'static str, f64)>,
    /// The same frame without its filler and with the crack probe, when it has a filler.
    pub unfilled: Option<Unfilled>,
}

impl Measured {
    /// The method's measure `name`, if it reported one.
    pub fn method_measure(&self, name: &str) -> Option<f64> {
        self.method_measures
            .iter()
            .find(|(n, _)| *n == name)
            .map(|&(_, v)| v)
    }
}

/// Bytes the whole database holds with every texture level, as the scene counts them for a
/// method with MapBlocks, plus an atlas slot per tile for the projected grids and the
/// quadtree patches estimated from their bodies' size (what methods hold beside the tiles;
/// [`whole_database_bytes_from`] counts the patches exactly).
pub fn whole_database_bytes(manifest: &Manifest) -> u64 {
    tiles_bytes(manifest)
        + manifest.patches.as_ref().map_or(0, |p| {
            crate::method::quadtree_patches::estimated_bytes(p.bodies_bytes)
        })
}

/// [`whole_database_bytes`] with the quadtree patches counted patch by patch from their
/// index, fetched from `server` ([`crate::method::quadtree_patches::expected_bytes`]): what
/// a scene must be allowed to hold every patch whole.
pub async fn whole_database_bytes_from(
    server: &str,
    manifest: &Manifest,
) -> Result<u64, FlightError> {
    use terrain_shared::quadtree;
    let Some(info) = &manifest.patches else {
        return Ok(whole_database_bytes(manifest));
    };
    let client = crate::http_client::TileClient::new(server)?;
    let bytes = client
        .blob(
            &terrain_shared::routes::patch_index(&manifest.content_version),
            Some(&info.index.hash),
            Some(info.index.bytes),
        )
        .await?;
    let entries = quadtree::decode_index(&bytes, manifest.tile_count())
        .map_err(|e| FlightError::BadOption(format!("the quadtree patches' index: {e}")))?;
    let tree = quadtree::Tree::for_tile_size(manifest.tile_size);
    let patches: u64 = manifest
        .tiles()
        .zip(&entries)
        .map(|((id, _), e)| crate::method::quadtree_patches::expected_bytes(e, tree, id.level))
        .sum();
    Ok(tiles_bytes(manifest) + patches)
}

/// [`whole_database_bytes`] less the quadtree patches.
fn tiles_bytes(manifest: &Manifest) -> u64 {
    let copies = crate::render::blocks::TEXTURE_COPIES;
    // The finer levels' encoded sizes per tile are in the tile blobs; the manifest gives
    // their totals.
    let finer_encoded: u64 = manifest.texture.level_bytes.iter().skip(1).sum();
    let finer_rgba: u64 = (1..manifest.texture.levels)
        .map(|l| u64::from(manifest.texture.level_size(l)).pow(2) * 4 * copies)
        .sum();
    manifest
        .tiles()
        .map(|(_, t)| expected_tile_bytes(manifest, t, copies).total() + finer_rgba)
        .sum::<u64>()
        + finer_encoded
        // The projected grids' atlas slot per tile: what they hold beside the tiles.
        + manifest.tile_count() as u64 * crate::method::projected_grid::atlas::slot_bytes_for(manifest)
}

impl Session {
    /// Connects to `server` and sets up a scene holding at most `memory_limit` bytes of tiles
    /// (`None`: the whole database, with a margin), drawn by `config` into `size` frames.
    /// Must run inside a multi-threaded tokio runtime.
    pub async fn open(
        server: &str,
        memory_limit: Option<u64>,
        config: RenderConfig,
        size: (u32, u32),
    ) -> Result<Session, FlightError> {
        let connection = Scene::connect(
            server,
            FetcherConfig::default(),
            tokio::runtime::Handle::current(),
        )
        .await?;
        let manifest = Arc::clone(&connection.manifest);
        let gpu = Gpu::headless()?;
        let target = Offscreen::new(&gpu, size.0, size.1);
        let whole = match memory_limit {
            Some(_) => 0,
            None => whole_database_bytes_from(server, &manifest).await? / 10 * 11 + (1 << 20),
        };
        let mut scene = connection.scene(
            memory_limit.unwrap_or(whole),
            true,
            Some((
                gpu.clone(),
                crate::render::offscreen::OFFSCREEN_FORMAT,
                config,
            )),
        );
        scene.set_viewport([size.0, size.1]);
        let least = scene.least_limit();
        match memory_limit {
            // The whole database, and what the method reserves beside it.
            None => scene.set_memory_limit(whole + least.method_bytes),
            Some(limit) => crate::memory::MemoryBudget {
                budget_bytes: limit,
                limit_percent: 100.0,
                source: crate::memory::BudgetSource::Given,
            }
            .check(
                least,
                &format!("--method {} at {}x{}", config.method.name(), size.0, size.1),
            )?,
        }
        scene.keep_depth(true);
        // Measured frames: each one's time runs to its completion on the GPU.
        scene.wait_for_each_frame(true);
        let fetcher = connection.fetcher;
        Ok(Session {
            manifest,
            scene,
            fetcher,
            gpu,
            target,
            config,
            frame: 0,
            method_measures: Vec::new(),
        })
    }

    /// The centre of the terrain at its highest point: where to stand to page in all of it.
    pub fn centre(&self) -> [f64; 3] {
        [
            self.manifest.extent_m[0] / 2.0,
            self.manifest.extent_m[1] / 2.0,
            self.manifest.heights.max_m + 100.0,
        ]
    }

    /// Paging, streaming and textures for a viewpoint at `position`, one frame's worth.
    pub async fn update(&mut self, position: [f64; 3]) -> Result<Update, FlightError> {
        tokio::task::yield_now().await;
        let update = self.scene.update(&mut self.fetcher, self.frame, position)?;
        self.frame += 1;
        Ok(update)
    }

    /// Updates at `position` until the scene has settled (nothing in flight, textures at
    /// their targets) or `timeout` passes; a frame is drawn from `camera` each time so that
    /// textures are shared by importance. Returns whether it settled.
    pub async fn settle(
        &mut self,
        position: [f64; 3],
        camera: &Camera,
        timeout: Duration,
    ) -> Result<bool, FlightError> {
        // Waiting is not an interactive frame: every level that has arrived is uploaded at
        // once instead of a few a frame (the measured frames then draw a scene that no
        // longer changes, whatever the cap).
        let cap = self.scene.set_uploads_per_frame(usize::MAX);
        let settled = self.settle_loop(position, camera, timeout).await;
        self.scene.set_uploads_per_frame(cap);
        settled
    }

    async fn settle_loop(
        &mut self,
        position: [f64; 3],
        camera: &Camera,
        timeout: Duration,
    ) -> Result<bool, FlightError> {
        let started = Instant::now();
        self.update(position).await?;
        loop {
            let drawing = Instant::now();
            self.scene.draw(&self.target.view, camera, Instant::now());
            let drew = drawing.elapsed();
            if self.scene.settled() {
                return Ok(true);
            }
            if started.elapsed() > timeout {
                return Ok(false);
            }
            // The fetcher starts requests only when polled, and a draw can take seconds (a
            // million triangles on a software rasterizer): between two draws, poll for as
            // long as the last one took, so that the requests do not wait on the frames.
            let until = Instant::now() + drew.max(Duration::from_millis(20));
            loop {
                tokio::time::sleep(Duration::from_millis(2)).await;
                self.update(position).await?;
                if Instant::now() >= until {
                    break;
                }
            }
        }
    }

    /// What keeps the scene from having settled, `None` once settled
    /// ([`Scene::unsettled`]).
    pub fn unsettled(&self) -> Option<String> {
        self.scene.unsettled()
    }

    /// Switches to `config` and, if its method wants data of its own (the quadtree
    /// patches), updates at `position` until it has it (see [`Session::settle`]); a method
    /// built anew asks for its data again.
    pub async fn prepare(
        &mut self,
        position: [f64; 3],
        camera: &Camera,
        config: RenderConfig,
        timeout: Duration,
    ) -> Result<bool, FlightError> {
        self.reconfigure(config);
        self.settle(position, camera, timeout).await
    }

    /// Draws the frame seen from `camera` with the session's current configuration.
    pub fn draw(&mut self, camera: &Camera) -> Option<DrawReport> {
        self.scene.draw(&self.target.view, camera, Instant::now())
    }

    /// Draws with `config` and reads the frame back.
    pub fn capture(
        &mut self,
        camera: &Camera,
        config: RenderConfig,
    ) -> Result<(Capture, DrawReport), FlightError> {
        self.reconfigure(config);
        let report = self.draw(camera).unwrap_or_default();
        self.method_measures = self.scene.method_measures();
        let color = self.target.read(&self.gpu)?;
        let depth = self
            .scene
            .read_depth()
            .unwrap_or_else(|| Err(crate::render::GpuError::Readback("no renderer".into())))?;
        Ok((Capture::new(color, depth, camera), report))
    }

    /// The reference frame at `camera`: every visible resident tile at full resolution.
    pub fn reference(&mut self, camera: &Camera) -> Result<(Capture, DrawReport), FlightError> {
        let config = RenderConfig {
            method: MethodKind::Reference,
            budget: BudgetMode::Fixed(u32::MAX),
            ..self.config
        };
        self.capture(camera, config)
    }

    /// Draws `camera`'s frame with `config` `repeats` times (timing each), reads the last one
    /// back and measures it against `reference`. With a crack filler the frame is also drawn
    /// without it, to tell filler pixels from surface pixels. A predicted (adaptive) budget
    /// is frozen at its current value first, so that every draw of the frame plans the same
    /// masks.
    pub fn measure(
        &mut self,
        camera: &Camera,
        config: RenderConfig,
        reference: &Capture,
        threshold_px: f64,
        repeats: u32,
    ) -> Result<Measured, FlightError> {
        let config = match (config.budget, self.scene.budget()) {
            (BudgetMode::Adaptive { .. }, Some(now)) => RenderConfig {
                budget: BudgetMode::Fixed(now),
                ..config
            },
            _ => config,
        };
        let unfilled = self.unfilled_depth(camera, config)?;
        self.reconfigure(config);
        let mut times = Vec::new();
        let mut gpu_times = Vec::new();
        for _ in 1..repeats.max(1) {
            if let Some(r) = self.draw(camera) {
                times.push(r.draw_ms);
                gpu_times.extend(r.stats.gpu_ms);
            }
        }
        let (capture, report) = self.capture(camera, config)?;
        times.push(report.draw_ms);
        gpu_times.extend(report.stats.gpu_ms);
        let scene = &self.scene;
        let measures = measure(
            &capture,
            unfilled.as_ref(),
            reference,
            camera,
            |x, y| scene.surface_height(x, y),
            threshold_px,
        );
        Ok(Measured {
            measures,
            report,
            frame_ms: median(&mut times),
            gpu_ms: (!gpu_times.is_empty()).then(|| median(&mut gpu_times)),
            capture,
            held_bytes: self.scene.cpu_bytes() + self.scene.gpu_bytes(),
            method_measures: std::mem::take(&mut self.method_measures),
            unfilled,
        })
    }

    /// With a crack filler, the depths of `camera`'s frame drawn without it and with the
    /// crack probe ([`Unfilled`]); `None` for a configuration without a filler.
    fn unfilled_depth(
        &mut self,
        camera: &Camera,
        config: RenderConfig,
    ) -> Result<Option<Unfilled>, FlightError> {
        if !config.method.uses_filler() || config.filler == CrackFiller::None {
            return Ok(None);
        }
        let with = |filler| RenderConfig { filler, ..config };
        let depth = self.capture(camera, with(CrackFiller::None))?.0.depth;
        let probe = self.capture(camera, with(CrackFiller::CrackProbe))?.0.depth;
        Ok(Some(Unfilled { depth, probe }))
    }

    /// Draws `camera`'s frame with `config` once and measures it against `reference`, a
    /// frame drawn by another session, with `truth`'s resident samples as the true surface
    /// (a scene holding the whole database; this one may hold too little of level 0 to
    /// know it).
    pub fn measure_against(
        &mut self,
        camera: &Camera,
        config: RenderConfig,
        reference: &Capture,
        truth: &Scene,
        threshold_px: f64,
    ) -> Result<Measured, FlightError> {
        let unfilled = self.unfilled_depth(camera, config)?;
        let (capture, report) = self.capture(camera, config)?;
        let measures = measure(
            &capture,
            unfilled.as_ref(),
            reference,
            camera,
            |x, y| truth.surface_height(x, y),
            threshold_px,
        );
        Ok(Measured {
            measures,
            frame_ms: report.draw_ms,
            gpu_ms: report.stats.gpu_ms,
            report,
            capture,
            held_bytes: self.scene.cpu_bytes() + self.scene.gpu_bytes(),
            method_measures: std::mem::take(&mut self.method_measures),
            unfilled,
        })
    }

    /// The screen-space error of `capture` itself against the true surface: for the
    /// reference, the floor of the measure (pixels the renderer itself gets wrong: a
    /// rasterizer's pinhole showing a point under the surface, a depth taken off a triangle
    /// seen edge-on past its exact edge).
    pub fn own_error(
        &self,
        capture: &Capture,
        camera: &Camera,
        threshold_px: f64,
    ) -> super::metrics::ErrorStats {
        let scene = &self.scene;
        super::metrics::screen_space_error(
            &capture.points,
            capture.color.width(),
            capture.color.height(),
            camera,
            |x, y| scene.surface_height(x, y),
            threshold_px,
        )
    }

    fn reconfigure(&mut self, config: RenderConfig) {
        self.scene.reconfigure(config);
    }

    /// Stops every request in flight.
    pub fn close(&mut self) {
        let all: Vec<_> = self.manifest.tiles().map(|(id, _)| id).collect();
        self.fetcher.cancel(&all);
    }
}

/// Median of `values` (0 for none); sorts them.
pub fn median(values: &mut [f64]) -> f64 {
    if values.is_empty() {
        return 0.0;
    }
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}
