//! Residency: what the scene holds and asks for. Deliveries become resident tiles, the
//! pager decides each level's square, requests are made, cancelled and retried, a new
//! manifest is reconciled with what is held, and what a frame's draw made past the
//! reservation is evicted again at its end.

use super::*;

impl Scene {
    /// Takes `manifest`, a newer one of the same server (its database was rebuilt), in
    /// place of the scene's. With the same grid, resident tiles whose heights and held
    /// texture levels have the same hashes stay; the others are dropped, to be fetched
    /// again from the new content; the method is built again for the new manifest. A grid
    /// of another shape cannot be taken: [`Reconciled::Reshaped`], and nothing changes.
    pub fn replace_manifest(&mut self, manifest: Arc<Manifest>) -> Reconciled {
        let old = &self.manifest;
        let same_shape = old.levels.len() == manifest.levels.len()
            && old
                .levels
                .iter()
                .zip(&manifest.levels)
                .all(|(a, b)| a.grid == b.grid && a.raster == b.raster)
            && old.tile_size == manifest.tile_size
            && old.spacing_m == manifest.spacing_m
            && old.mask_levels == manifest.mask_levels
            && old.texture.size == manifest.texture.size
            && old.texture.levels == manifest.texture.levels
            && old.texture.format == manifest.texture.format;
        if !same_shape {
            return Reconciled::Reshaped;
        }
        let (mut kept, mut dropped) = (0, 0);
        let changed: Vec<TileId> = self
            .manifest
            .tiles()
            .zip(manifest.tiles())
            .zip(&self.tiles)
            .filter(|(_, tile)| tile.is_some())
            .filter_map(|(((id, before), (_, after)), _)| {
                // The tile blob's hash covers its heights, its errors and its textures'
                // hashes: the same hash, the same tile.
                if before.hash == after.hash {
                    kept += 1;
                    None
                } else {
                    dropped += 1;
                    Some(id)
                }
            })
            .collect();
        for id in changed {
            self.drop_tile(id);
        }
        self.manifest = Arc::clone(&manifest);
        self.layout = Layout::of(&manifest);
        self.failing.clear();
        self.unavailable.clear();
        match &self.rendering {
            Some(r) => {
                let method = build_method(&r.renderer, &manifest, &r.config);
                // Teaches the method the kept tiles and recounts every tile's bytes and
                // what the pager expects of each.
                self.install(method);
            }
            None => {
                for (expected, (_, record)) in self.expected_bytes.iter_mut().zip(manifest.tiles())
                {
                    *expected = expected_tile_bytes(&manifest, record, 0).total();
                }
            }
        }
        Reconciled::Kept { kept, dropped }
    }

    /// Drops resident tile `id`, everywhere it is held.
    pub(super) fn drop_tile(&mut self, id: TileId) {
        let Some(i) = self.manifest.index(id) else {
            return;
        };
        if let Some(tile) = self.tiles[i].take()
            && !tile.used
        {
            self.evicted_unused_bytes += tile.downloaded;
        }
        self.base_bytes[i] = 0;
        if let Some(r) = &mut self.rendering {
            r.texture_costs[i] = Vec::new();
            r.renderer.tiles.remove_tile(id);
            r.method.tile_evicted(id);
            r.data_pending.retain(|(tile, _)| *tile != id);
        }
    }

    /// Deliveries, paging and the texture budget for a viewpoint at `position` (metres).
    pub fn update(
        &mut self,
        fetcher: &mut Fetcher,
        frame: u64,
        position: [f64; 3],
    ) -> Result<Update, SceneError> {
        for event in fetcher.poll() {
            self.deliver(event)?;
        }
        fetcher.mark_pending(&mut self.in_flight, &self.manifest);
        // A resident tile waiting for a finer texture is not "in flight" for the pager.
        for (flag, tile) in self.in_flight.iter_mut().zip(&self.tiles) {
            *flag &= tile.is_none();
        }
        // What the method holds, or may hold, for no tile in particular comes off the
        // tiles' share, and what is left is shared between the levels.
        let limit = self.pager.memory_limit.saturating_sub(self.reserve());
        let ranges: Vec<std::ops::Range<usize>> = (0..self.levels_used)
            .map(|k| {
                let start = self.manifest.level_offset(k);
                start..start + self.manifest.levels[k as usize].tiles.len()
            })
            .collect();
        let whole: Vec<u64> = ranges
            .iter()
            .map(|r| self.expected_bytes[r.clone()].iter().sum())
            .collect();
        let shares = page::shares_by(self.level_policy, limit, &whole);
        let now = Instant::now();
        self.in_square.fill(false);
        let mut levels = Vec::with_capacity(ranges.len());
        for (k, range) in ranges.into_iter().enumerate() {
            let level = k as u32;
            let grid = self.manifest.grid(level);
            // The paper's pager fetches the current tile even when it alone takes the
            // resident bytes over the limit. Here no level does: a current tile that does
            // not fit waits while cached belts are dropped to make room, so the limit holds
            // on every frame. A limit too small for the coarsest level used, which is held
            // whole, is refused at start ([`Scene::least_limit`]).
            let pager = PagerConfig {
                columns: grid.columns,
                rows: grid.rows,
                memory_limit: shares[k],
                current_over_limit: false,
                ..self.pager
            };
            let extent = self.layout.tile_extent_m_at(level);
            let view = PagerView {
                viewpoint: [position[0] / extent[0], position[1] / extent[1]],
                resident_bytes: &self.base_bytes[range.clone()],
                in_flight: &self.in_flight[range.clone()],
                expected_bytes: Some(&self.expected_bytes[range.clone()]),
            };
            let decision = page::decide(&pager, &view);
            let tag = |ids: &[TileId]| -> Vec<TileId> {
                ids.iter().map(|id| id.with_level(level)).collect()
            };
            fetcher.cancel(&tag(&decision.cancel));
            let evict = tag(&decision.evict);
            fetcher.cancel(&evict);
            for id in evict {
                self.drop_tile(id);
            }
            for (rank, id) in tag(&decision.fetch).into_iter().enumerate() {
                // A tile that failed waits out its delay; one given up is not asked for again.
                if let Some(failing) = self.failing.get(&id) {
                    if failing.failures >= TILE_REQUESTS_BEFORE_GIVING_UP || now < failing.retry_at
                    {
                        continue;
                    }
                    self.requests_repeated += 1;
                }
                // Earlier frames' requests go first; within a frame, coarser levels first
                // (they cover the most screen), then the pager's order.
                let order = (u64::from(self.levels_used - level) << 16) | rank as u64;
                fetcher.request(id, Want::Tile, (frame << 20) | order.min((1 << 18) - 1));
                if let Some(i) = self.manifest.index(id) {
                    self.in_flight[i] = true;
                }
            }
            for id in page::square_tiles(&pager, decision.current, decision.complete_belts) {
                let i = self.index(id.with_level(level));
                if let Some(flag) = self.in_square.get_mut(i) {
                    *flag = true;
                }
                if let Some(Some(tile)) = self.tiles.get_mut(i) {
                    tile.used = true;
                }
            }
            levels.push(LevelDecision {
                level,
                pager,
                decision,
            });
        }
        let decision = levels
            .first()
            .map(|l| l.decision.clone())
            .unwrap_or_else(|| {
                page::decide(
                    &self.pager,
                    &PagerView {
                        viewpoint: [0.0, 0.0],
                        resident_bytes: &[],
                        in_flight: &[],
                        expected_bytes: None,
                    },
                )
            });
        self.request_method_data(fetcher, frame);
        let texture_budget = self.share_textures(fetcher, frame);
        Ok(Update {
            decision,
            levels,
            texture_budget,
        })
    }

    /// Bytes kept for what the method holds for no tile in particular: what it may reach
    /// ([`LodMethod::reserved_bytes`]) or what it holds, whichever is more.
    pub(super) fn reserve(&self) -> u64 {
        self.rendering.as_ref().map_or(0, |r| {
            r.method
                .reserved_bytes(r.viewport)
                .max(r.method.shared_bytes().total())
        })
    }

    /// Asks the fetcher for the data the method wants of resident tiles, once each.
    pub(super) fn request_method_data(&mut self, fetcher: &mut Fetcher, frame: u64) {
        let Some(r) = &mut self.rendering else {
            return;
        };
        for want in r.method.wants() {
            let i = self.manifest.index(want.id).unwrap_or(usize::MAX);
            if self.tiles.get(i).is_none_or(Option::is_none)
                || !r.data_pending.insert((want.id, want.key))
            {
                continue;
            }
            // After the tiles of this frame and the textures, in the order asked.
            let priority = (frame << 20) | (1 << 19) | (1 << 18);
            fetcher.request_data(
                want.id, want.key, want.path, want.hash, want.bytes, priority,
            );
        }
    }

    pub(super) fn deliver(&mut self, event: FetchEvent) -> Result<(), SceneError> {
        match event {
            FetchEvent::Tile {
                id,
                heights,
                heights_bytes,
                mask_errors_m,
                texture,
                coarsest_texture,
                ..
            } => {
                let Some(i) = self.manifest.index(id) else {
                    return Ok(());
                };
                let heights = Arc::new(heights);
                let error_minima = crate::lod::needed::suffix_minima(&mask_errors_m);
                let mut bytes = TileBytes {
                    decoded_heights: std::mem::size_of_val(heights.codes.as_slice()) as u64
                        + error_table_bytes(&self.manifest),
                    textures: coarsest_texture.len() as u64,
                    ..TileBytes::default()
                };
                let mut uploaded_levels = 0;
                if let Some(r) = &mut self.rendering {
                    r.renderer.tiles.upload_tile(id, Arc::clone(&heights));
                    let gpu = r.renderer.gpu().clone();
                    r.method.tile_resident(&gpu, id, &heights);
                    if let Some(image) = decode_texture(&coarsest_texture, id, 0) {
                        r.renderer.tiles.upload_texture(id, 0, &[image]);
                        uploaded_levels = 1;
                    }
                    bytes.gpu = r.renderer.tiles.tile_bytes(id);
                    bytes.method = r.method.tile_bytes(id);
                    let copies = r.config.method_config().texture_copies();
                    r.texture_costs[i] = extra_costs(&self.manifest, &texture, copies);
                }
                // What the method expects to hold for it and does not yet (data that arrive
                // after the tile) is reserved, so that the pager does not fill that room.
                let reserved =
                    self.rendering
                        .as_ref()
                        .zip(self.manifest.tile(id))
                        .map_or(0, |(r, record)| {
                            r.method
                                .expected_tile_bytes(record)
                                .saturating_sub(bytes.method)
                        });
                self.base_bytes[i] = bytes.total() + reserved;
                self.tiles[i] = Some(ResidentTile {
                    heights,
                    error_minima,
                    texture_blobs: texture,
                    downloaded: heights_bytes + coarsest_texture.len() as u64,
                    textures: vec![coarsest_texture],
                    uploaded_levels,
                    undecodable_from: (uploaded_levels == 0 && self.rendering.is_some())
                        .then_some(0),
                    bytes,
                    used: false,
                });
                self.tiles_fetched += 1;
                self.failing.remove(&id);
            }
            FetchEvent::TextureLevel {
                id, level, bytes, ..
            } => {
                let Some(i) = self.manifest.index(id) else {
                    return Ok(());
                };
                let target = self.rendering.as_ref().map_or(0, |r| r.texture_target[i]);
                if let Some(tile) = &mut self.tiles[i]
                    && level as usize == tile.textures.len()
                    && level <= target
                {
                    tile.bytes.textures += bytes.len() as u64;
                    tile.downloaded += bytes.len() as u64;
                    tile.textures.push(bytes);
                }
            }
            FetchEvent::Data { id, key, bytes } => {
                let Some(i) = self.manifest.index(id) else {
                    return Ok(());
                };
                if let (Some(r), Some(tile)) = (&mut self.rendering, &mut self.tiles[i])
                    && r.data_pending.remove(&(id, key))
                {
                    tile.downloaded += bytes.len() as u64;
                    let gpu = r.renderer.gpu().clone();
                    r.method.data_arrived(&gpu, id, key, bytes);
                    tile.bytes.method = r.method.tile_bytes(id);
                    if let Some(record) = self.manifest.tile(id) {
                        self.base_bytes[i] = r.base_bytes(&self.manifest, record, tile);
                    }
                    // Data that changes what the method expects of other tiles (an index).
                    if r.method.bytes_changed() {
                        self.recount();
                    }
                }
            }
            FetchEvent::Failed {
                id, error, want, ..
            } => {
                // A tile the server refuses (4xx) will never arrive: the flight cannot
                // complete its square, so it stops with the server's reason. Corrupt or
                // unreachable tiles are asked for again on a later frame.
                if let (Want::Data(key), Some(r)) = (want, &mut self.rendering) {
                    // Asked again on a later frame, if the method still wants it.
                    r.data_pending.remove(&(id, key));
                }
                if want == Want::Tile && FailureKind::of(&error) == FailureKind::Permanent {
                    return Err(SceneError::TileFailed {
                        id,
                        message: error.chain(),
                    });
                }
                if want != Want::Tile {
                    tracing::warn!(tile = %id, ?want, "request failed: {}", error.chain());
                    return Ok(());
                }
                let failing = self.failing.entry(id).or_insert(TileFailures {
                    failures: 0,
                    retry_at: Instant::now(),
                });
                failing.failures += 1;
                let delay = TILE_RETRY_DELAY * (1 << (failing.failures - 1).min(16));
                failing.retry_at = Instant::now() + delay;
                if failing.failures >= TILE_REQUESTS_BEFORE_GIVING_UP {
                    tracing::warn!(
                        tile = %id,
                        "tile given up after {} failed requests; the square will not grow past it: {}",
                        failing.failures,
                        error.chain()
                    );
                    self.unavailable.push(UnavailableTile {
                        id,
                        failures: failing.failures,
                        error: error.chain(),
                    });
                } else {
                    tracing::warn!(
                        tile = %id,
                        "tile request failed; asking again in {:.0} s: {}",
                        delay.as_secs_f64(),
                        error.chain()
                    );
                }
            }
        }
        Ok(())
    }

    /// Brings what the scene holds back under its limit at a frame's end, when the
    /// method's index sets grew past its reservation during the draw: first what the method
    /// holds and the frame did not use ([`LodMethod::trim`]), then finer texture levels,
    /// least important tiles first, then resident tiles the frame did not draw, then tiles
    /// it drew, least important and farthest from `eye` first; never a tile of the coarsest
    /// level used, which is held whole. Returns the tiles dropped (0 unless the method's
    /// working set outgrew what the pager left it); the pager sees the room they leave
    /// taken by the method on the next frame, and does not fetch them again into it.
    pub(super) fn enforce_limit(&mut self, drawn: &[bool], eye: [f64; 3]) -> u32 {
        let limit = self.pager.memory_limit;
        if self.resident_bytes() <= limit {
            return 0;
        }
        let over = self.resident_bytes().saturating_sub(limit);
        if let Some(r) = &mut self.rendering {
            r.method.trim(over);
        }
        self.shed_textures();
        let mut squeezed = 0;
        if self.resident_bytes() > limit {
            let coarsest = self.levels_used.saturating_sub(1);
            let mut order: Vec<usize> = (0..self.tiles.len())
                .filter(|&i| self.tiles[i].is_some() && self.manifest.id_at(i).level < coarsest)
                .collect();
            let importance = |i: usize| {
                self.rendering
                    .as_ref()
                    .map_or(0.0, |r| r.importance.get(i).copied().unwrap_or(0.0))
            };
            let distance = |i: usize| {
                let id = self.manifest.id_at(i);
                let [x0, y0] = self.layout.tile_origin_m(id);
                let [w, h] = self.layout.tile_extent_m_at(id.level);
                (x0 + w / 2.0 - eye[0]).hypot(y0 + h / 2.0 - eye[1])
            };
            order.sort_by(|&a, &b| {
                drawn[a]
                    .cmp(&drawn[b])
                    .then(importance(a).total_cmp(&importance(b)))
                    .then(distance(b).total_cmp(&distance(a)))
            });
            for i in order {
                if self.resident_bytes() <= limit {
                    break;
                }
                let id = self.manifest.id_at(i);
                self.drop_tile(id);
                squeezed += 1;
            }
            if squeezed > 0 {
                tracing::debug!(
                    tiles = squeezed,
                    "the method's index sets outgrew its reservation: tiles dropped to keep the limit"
                );
            }
        }
        squeezed
    }
}
