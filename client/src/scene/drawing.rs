//! Drawing and its accounting: the method that plans each frame, the frame-rate
//! controller fed with what frames cost, and the bytes the method and the renderer hold on
//! the GPU and beside it.

use super::*;

/// The bytes a scene keeps for its terrain's geometry ([`Scene::geometry_memory`]): what the
/// GeoMipMaps paper counts in its bytes per sample (heights, level-of-detail data, index
/// sets), textures apart.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct GeometryMemory {
    /// Samples of the resident tiles (shared borders counted in each tile, as stored).
    pub samples: u64,
    /// Decoded height codes (CPU), shared with the renderer.
    pub cpu_heights: u64,
    /// Per-tile error tables: the manifest's strip-mask errors and what the method holds
    /// on the CPU (its tables, strips).
    pub cpu_lod: u64,
    /// Pooled sample buffers (only tiles drawn lately hold one) and textures.
    pub gpu: crate::render::GpuResidency,
    /// The method's GPU bytes (index sets, buffers of its own).
    pub method_gpu: u64,
}

impl GeometryMemory {
    /// Geometry bytes: heights, error tables, sample buffers and the method's GPU bytes.
    pub fn bytes(&self) -> u64 {
        self.cpu_heights + self.cpu_lod + self.gpu.sample_bytes + self.method_gpu
    }

    /// [`GeometryMemory::bytes`] per resident sample.
    pub fn per_sample(&self) -> f64 {
        self.bytes() as f64 / self.samples.max(1) as f64
    }

    /// GPU geometry per resident sample (the samples held on the GPU and the method's index
    /// sets and buffers) if every resident tile held its samples there: the most the GPU
    /// keeps for this resident set, what the strip-mask paper counts.
    pub fn gpu_per_sample_all_held(&self) -> f64 {
        let per_slot = self
            .gpu
            .sample_bytes
            .checked_div(self.gpu.sample_buffers)
            .unwrap_or(0);
        (per_slot * self.gpu.tiles + self.method_gpu) as f64 / self.samples.max(1) as f64
    }
}

impl std::fmt::Display for GeometryMemory {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let per = |b: u64| b as f64 / self.samples.max(1) as f64;
        write!(
            f,
            "{:.2} B/sample: heights {:.2}, error tables {:.3}, GPU samples {:.2} ({} of {} tiles hold a buffer), method GPU (index sets) {:.3}; GPU geometry {:.2} B/sample, {:.2} with every resident tile's samples held",
            self.per_sample(),
            per(self.cpu_heights),
            per(self.cpu_lod),
            per(self.gpu.sample_bytes),
            self.gpu.sample_buffers,
            self.gpu.tiles,
            per(self.method_gpu),
            per(self.gpu.sample_bytes + self.method_gpu),
            self.gpu_per_sample_all_held(),
        )
    }
}

impl Scene {
    /// What the scene keeps for its geometry now (see [`GeometryMemory`]).
    pub fn geometry_memory(&self) -> GeometryMemory {
        let resident = self.tiles.iter().flatten();
        GeometryMemory {
            samples: self.resident_tiles() * u64::from(self.manifest.tile_size).pow(2),
            cpu_heights: resident.map(|t| t.bytes.decoded_heights).sum(),
            cpu_lod: self
                .tiles
                .iter()
                .flatten()
                .map(|t| 4 * t.error_minima.len() as u64)
                .sum::<u64>()
                + self.rendering.as_ref().map_or(0, |r| {
                    let per_tile: u64 = self.tiles.iter().flatten().map(|t| t.bytes.method).sum();
                    per_tile + r.method.shared_bytes().cpu
                }),
            gpu: self
                .rendering
                .as_ref()
                .map_or_else(Default::default, |r| r.renderer.tiles.residency()),
            method_gpu: self.rendering.as_ref().map_or(0, |r| r.method.gpu_bytes()),
        }
    }

    /// Sets how many texture levels a frame uploads at most
    /// ([`RenderConfig::uploads_per_frame`]) and returns the number it replaces; the method
    /// and everything else stay as they are.
    pub fn set_uploads_per_frame(&mut self, uploads: usize) -> usize {
        self.rendering.as_mut().map_or(uploads, |r| {
            std::mem::replace(&mut r.config.uploads_per_frame, uploads)
        })
    }

    /// Draws later frames with `config`'s method and settings; a different budget mode
    /// starts the frame-rate controller again. Resident tiles stay. Nothing happens without
    /// rendering.
    pub fn reconfigure(&mut self, config: RenderConfig) {
        let Some(r) = &mut self.rendering else {
            return;
        };
        let method = (config.method != r.config.method)
            .then(|| build_method(&r.renderer, &self.manifest, &config));
        if method.is_none() {
            // Same method: new settings, and whatever it learnt of the tiles stays.
            r.method.configure(&config.method_config());
        }
        if config.budget != r.config.budget {
            r.controller = FrameRateController::new(
                config.budget,
                crate::render::frame::FRAMES_IN_FLIGHT as usize,
            );
        }
        r.config = config;
        match method {
            Some(method) => self.install(method),
            None => self.recount(),
        }
    }

    /// Draws later frames with the method `make` builds (one of the scene's configuration's
    /// kind, or any other [`LodMethod`]). Resident tiles stay; the method learns them.
    /// Nothing happens without rendering.
    pub fn use_method(&mut self, make: impl FnOnce(&method::Build<'_>) -> Box<dyn LodMethod>) {
        let Some(r) = &self.rendering else {
            return;
        };
        let method = make(&method::Build {
            gpu: r.renderer.gpu(),
            format: r.renderer.format(),
            frame_layout: r.renderer.frame_bind_group_layout(),
            manifest: &self.manifest,
        });
        self.install(method);
    }

    /// Makes `method` the scene's, teaching it the resident tiles.
    pub(super) fn install(&mut self, method: Box<dyn LodMethod>) {
        let Some(r) = &mut self.rendering else {
            return;
        };
        r.method = method;
        r.data_pending.clear();
        let gpu = r.renderer.gpu().clone();
        for ((id, _), tile) in self.manifest.tiles().zip(&self.tiles) {
            if let Some(tile) = tile {
                r.method.tile_resident(&gpu, id, &tile.heights);
            }
        }
        self.recount();
    }

    /// MapBlocks as the configuration wants, and what each tile is charged and the pager
    /// expects of each, after a change of method or settings.
    pub(super) fn recount(&mut self) {
        let Some(r) = &mut self.rendering else {
            return;
        };
        r.set_texture_blocks(&self.manifest);
        let copies = r.config.method_config().texture_copies();
        // What each tile is charged, and what the pager expects of each, follow the method
        // and the copies of each GPU texture.
        for (i, ((id, record), tile)) in self.manifest.tiles().zip(&mut self.tiles).enumerate() {
            self.expected_bytes[i] = r.expected_tile_bytes(&self.manifest, record).total();
            if let Some(tile) = tile {
                r.texture_costs[i] = extra_costs(&self.manifest, &tile.texture_blobs, copies);
                tile.bytes.gpu = r.renderer.tiles.tile_bytes(id);
                tile.bytes.method = r.method.tile_bytes(id);
                self.base_bytes[i] = r.base_bytes(&self.manifest, record, tile);
            }
        }
    }

    /// The triangle budget of the next frame (`None` when not rendering).
    pub fn budget(&self) -> Option<u32> {
        self.rendering.as_ref().map(|r| r.controller.budget())
    }

    /// Keeps each frame's depth buffer for [`Scene::read_depth`] (slower; for measuring).
    pub fn keep_depth(&mut self, keep: bool) {
        if let Some(r) = &mut self.rendering {
            r.renderer.keep_depth(keep);
        }
    }

    /// Makes [`Scene::draw`] wait for each frame to finish on the GPU, so that its
    /// [`DrawReport::draw_ms`] and GPU time are that frame's: for measurements (the
    /// evaluation). Off by default: a flight or a window never waits for its frames.
    pub fn wait_for_each_frame(&mut self, wait: bool) {
        if let Some(r) = &mut self.rendering {
            r.wait_for_gpu = wait;
        }
    }

    /// The last frame's depth buffer (see [`Renderer::read_depth`]).
    pub fn read_depth(&self) -> Option<Result<Vec<f32>, crate::render::GpuError>> {
        self.rendering.as_ref().map(|r| r.renderer.read_depth())
    }

    /// What the level choice ([`crate::lod::levels::choose`]) knows of resident tile `id`:
    /// its bounds and its own surface's deviation from full resolution. `None` when not
    /// resident.
    /// (An associated function of the parts it reads, so that [`Scene::draw`] can call it
    /// while it holds the rendering state.)
    fn held_for_choice(
        manifest: &Manifest,
        tiles: &[Option<ResidentTile>],
        id: TileId,
    ) -> Option<crate::lod::levels::Held> {
        let tile = tiles.get(manifest.index(id)?)?.as_ref()?;
        let record = manifest.tile(id)?;
        Some(crate::lod::levels::Held {
            min_m: f64::from(record.min_m),
            max_m: f64::from(record.max_m),
            deviation_m: tile.error_minima.first().copied().unwrap_or(0.0),
        })
    }

    /// The byte oracle of a view: the tiles the level choice ([`crate::lod::levels::choose`])
    /// draws for `camera` on `viewport` when the whole pyramid is resident, the coarsest of
    /// each visible part within `threshold_px` of full resolution by its builder-measured
    /// deviation, and what they cost: held as the pager counts a tile at its coarsest
    /// texture ([`expected_tile_bytes`] with the method's share), and downloaded (tile blob
    /// and coarsest texture level). A tile not resident is passed over for its children, so
    /// the answer is the oracle's only when every tile is resident.
    pub fn bytes_needed(
        &self,
        camera: &Camera,
        viewport: [u32; 2],
        threshold_px: f64,
    ) -> Vec<(TileId, NeededBytes)> {
        let chosen = crate::lod::levels::choose(
            &self.manifest,
            &self.layout,
            self.manifest.level_count(),
            camera,
            viewport,
            threshold_px,
            |id| Self::held_for_choice(&self.manifest, &self.tiles, id),
        );
        chosen
            .into_iter()
            .filter_map(|id| {
                let i = self.manifest.index(id)?;
                let record = self.manifest.tile(id)?;
                Some((
                    id,
                    NeededBytes {
                        held: self.expected_bytes[i],
                        downloaded: record.bytes + record.coarsest_texture_bytes,
                    },
                ))
            })
            .collect()
    }

    /// Plans and renders a frame seen from `camera` into `target`, then feeds its time to
    /// the frame-rate controller. `frame_started` is when the frame's work began, so that
    /// the controller sees the whole frame: for frames drawn back to back (a flight), the
    /// end of the draw before it; after a wait that is no work of the frame's (a window's
    /// vsync), the end of that wait. `None` when not rendering.
    pub fn draw(
        &mut self,
        target: &wgpu::TextureView,
        camera: &Camera,
        frame_started: Instant,
    ) -> Option<DrawReport> {
        let r = self.rendering.as_mut()?;
        let started = Instant::now();
        let size = target.texture().size();
        r.viewport = [size.width, size.height];
        let levels_drawn = if r.method.full_resolution_only() {
            1
        } else {
            self.levels_used
        };
        let chosen = crate::lod::levels::choose(
            &self.manifest,
            &self.layout,
            levels_drawn,
            camera,
            [size.width, size.height],
            r.config.lod.max_error_px,
            |id| {
                let i = self.manifest.index(id)?;
                (self.in_square[i] || !r.config.square_only)
                    .then(|| Self::held_for_choice(&self.manifest, &self.tiles, id))
                    .flatten()
            },
        );
        let seams = crate::lod::levels::seams(&chosen);
        let candidates: Vec<Candidate> = chosen
            .iter()
            .zip(seams)
            .filter_map(|(&id, seams)| {
                let i = self.manifest.index(id)?;
                let tile = self.tiles[i].as_ref()?;
                Some(Candidate {
                    seams,
                    ..Candidate::new(id, self.manifest.tile(id)?, &tile.error_minima)
                })
            })
            .collect();
        let resident: Vec<(TileId, f32)> = if r.method.needs_every_resident_tile() {
            (0..levels_drawn)
                .flat_map(|level| {
                    let offset = self.manifest.level_offset(level);
                    let columns = self.manifest.grid(level).columns.max(1);
                    let count = self.manifest.levels[level as usize].tiles.len();
                    (0..count).map(move |k| {
                        let id = TileId::at(level, k as u32 % columns, k as u32 / columns);
                        (offset + k, id)
                    })
                })
                .filter_map(|(i, id)| {
                    let tile = self.tiles[i].as_ref()?;
                    Some((id, tile.error_minima.first().copied().unwrap_or(0.0)))
                })
                .collect()
        } else {
            Vec::new()
        };
        let room = self
            .pager
            .memory_limit
            .saturating_sub(self.resident_bytes())
            + self.sheddable_texture_bytes();
        let r = self.rendering.as_mut()?;
        let input = MethodInput {
            layout: &self.layout,
            tiles: &candidates,
            resident: &resident,
            budget: r.controller.budget(),
            room,
        };
        let mut frame = r.renderer.begin_frame(target, camera);
        let out = r.method.draw(&input, &mut frame);
        let mut stats = frame.finish();
        let (plan, lod_ms) = (out.plan, out.lod_ms);
        r.importance.fill(0.0);
        let mut drawn = vec![false; self.tiles.len()];
        for (id, importance) in out.importance {
            if let Some(i) = self.manifest.index(id) {
                r.importance[i] = importance;
                drawn[i] = true;
            }
        }
        for d in &plan.draws {
            if let Some(i) = self.manifest.index(d.id) {
                drawn[i] = true;
            }
        }
        // What the method holds per tile changed (its own data meshed since): counted again.
        if r.method.bytes_changed() {
            self.recount();
        }
        // A method's index sets and buffers grow as frames need them: what they took past
        // the limit comes off at once, so that the limit holds at the frame's end.
        stats.squeezed_tiles = self.enforce_limit(&drawn, camera.position);
        // A frame that made, replaced or dropped GPU allocations of the terrain waits for
        // its completion: what it dropped is still used by the frames in flight, and is
        // freed only once they finish, so the memory limit holds at every frame's end.
        // The others (a steady view) do not wait.
        let r = self.rendering.as_mut()?;
        let allocations = (r.renderer.tiles.allocation_epoch(), r.method.gpu_bytes());
        let changed = allocations != r.allocations;
        r.allocations = allocations;
        if r.wait_for_gpu || changed {
            match r.renderer.wait_for_gpu() {
                Ok(gpu_ms) => stats.gpu_ms = gpu_ms,
                Err(e) => tracing::warn!(error = %e, "the frame did not finish"),
            }
        }
        let draw_ms = started.elapsed().as_secs_f64() * 1e3;
        let frame_s = frame_started.elapsed().as_secs_f64();
        // Only a method that shares the budget out adapts to it; the others (GeoMipMaps,
        // the grids, the patches, the reference) are set by their error threshold or grid.
        let target_fps = if r.method.uses_budget() {
            r.controller.target_fps()
        } else {
            None
        };
        let predicted_ms = target_fps
            .and(r.controller.predicted_seconds(stats.triangles))
            .map(|s| s * 1e3);
        if r.method.uses_budget() {
            r.controller.next_budget(FrameCost {
                triangles: stats.triangles,
                wanted: if r.config.lod.cap_at_needed {
                    plan.triangles_needed
                } else {
                    u64::MAX
                },
                seconds: frame_s,
            });
        }
        Some(DrawReport {
            triangles_needed: plan.triangles_needed,
            method: r.method.name(),
            plan,
            stats,
            lod_ms,
            draw_ms,
            frame_ms: frame_s * 1e3,
            predicted_ms,
            target_fps,
        })
    }
}

/// Builds `config`'s method for `renderer`'s device and targets.
pub(super) fn build_method(
    renderer: &Renderer,
    manifest: &Manifest,
    config: &RenderConfig,
) -> Box<dyn LodMethod> {
    method::build(
        &config.method_config(),
        &method::Build {
            gpu: renderer.gpu(),
            format: renderer.format(),
            frame_layout: renderer.frame_bind_group_layout(),
            manifest,
        },
    )
}

impl Rendering {
    /// What a tile holds once resident at its coarsest texture: [`expected_tile_bytes`]
    /// with this configuration's texture copies, and what the method expects to hold for it.
    pub(super) fn expected_tile_bytes(
        &self,
        manifest: &Manifest,
        tile: &terrain_shared::TileRecord,
    ) -> TileBytes {
        TileBytes {
            method: self.method.expected_tile_bytes(tile),
            ..expected_tile_bytes(manifest, tile, self.config.method_config().texture_copies())
        }
    }

    /// What the pager counts for resident `tile`: its bytes at its coarsest texture (finer
    /// levels are paid from the texture budget) and what the method holds for it, or
    /// expects to hold once its data are in, whichever is more.
    pub(super) fn base_bytes(
        &self,
        manifest: &Manifest,
        record: &terrain_shared::TileRecord,
        tile: &ResidentTile,
    ) -> u64 {
        let copies = self.renderer.tiles.texture_copies();
        let gpu_texture = if tile.uploaded_levels > 0 {
            coarsest_rgba_bytes(manifest)
        } else {
            // The grey texel it draws with until a level decodes.
            4
        };
        tile.bytes.decoded_heights
            + tile.textures.first().map_or(0, |t| t.len() as u64)
            + self.renderer.tiles.sample_buffer_bytes()
            + copies * gpu_texture
            // What the method holds, or expects to hold once its data are in.
            + tile.bytes.method.max(self.method.expected_tile_bytes(record))
    }

    /// MapBlocks on or off as the method wants, and the texture costs that follow (a block
    /// texture copies its tiles' textures).
    pub(super) fn set_texture_blocks(&mut self, manifest: &Manifest) {
        let blocks = self.config.method_config().uses_texture_blocks();
        self.renderer.tiles.set_texture_blocks(blocks.then(|| {
            let grid = manifest.grid(0);
            crate::render::blocks::BlockLayout::new(
                [grid.columns, grid.rows],
                manifest
                    .texture
                    .level_size(manifest.texture.levels.saturating_sub(1)),
                self.config
                    .texture_block_limit
                    .unwrap_or(self.renderer.tiles.max_texture_side()),
            )
        }));
    }
}
