//! The texture budget: what the limit leaves once the tiles in flight are paid for sets how
//! fine each resident tile's texture goes, dropping levels at once and asking for finer
//! ones one at a time; under pressure the finer levels go first.

use super::*;

impl Scene {
    /// Shares the texture budget, drops levels over it, uploads levels that arrived and
    /// requests the next finer level of tiles under their target. Returns the budget.
    pub(super) fn share_textures(&mut self, fetcher: &mut Fetcher, frame: u64) -> u64 {
        let Some(r) = &mut self.rendering else {
            return 0;
        };
        let base: u64 = self.base_bytes.iter().sum();
        let coming: u64 = self
            .in_flight
            .iter()
            .zip(&self.expected_bytes)
            .filter(|(f, _)| **f)
            .map(|(_, b)| b)
            .sum();
        let shared = r
            .method
            .reserved_bytes(r.viewport)
            .max(r.method.shared_bytes().total());
        let budget = self
            .pager
            .memory_limit
            .saturating_sub(base + coming + shared);
        let mut indices = Vec::new();
        let mut candidates = Vec::new();
        for (i, tile) in self.tiles.iter().enumerate() {
            if tile.is_none() {
                continue;
            }
            indices.push(i);
            candidates.push(TextureCandidate {
                importance: r.importance[i],
                extra_cost: &r.texture_costs[i],
            });
        }
        let targets = share_texture_budget(&candidates, budget);
        // Levels to keep: what each tile holds, unless the held levels together exceed the
        // budget; then the least important tiles drop to their target first. Dropping only
        // when the limit demands it keeps textures from being dropped and fetched again as
        // importances shift from frame to frame.
        let held = |i: usize| self.tiles[i].as_ref().map_or(1, |t| t.textures.len()) as u32 - 1;
        let mut keep: Vec<u32> = indices.iter().map(|&i| held(i)).collect();
        let mut spent: u64 = keep
            .iter()
            .zip(&candidates)
            .map(|(&l, c)| c.extra_cost.get(l as usize).copied().unwrap_or(0))
            .sum();
        if spent > budget {
            for k in most_important_first(&candidates).into_iter().rev() {
                if spent <= budget {
                    break;
                }
                if keep[k] > targets[k] {
                    let cost = &candidates[k].extra_cost;
                    spent -= cost[keep[k] as usize] - cost[targets[k] as usize];
                    keep[k] = targets[k];
                }
            }
        }
        // The most important tiles first: their levels are asked for sooner and take the
        // frame's uploads before tiles out of view.
        let order = most_important_first(&candidates);
        let mut uploads = 0;
        for (rank, &k) in order.iter().enumerate() {
            let (i, target) = (indices[k], targets[k]);
            r.texture_target[i] = target.max(keep[k]);
            let Some(tile) = &mut self.tiles[i] else {
                continue;
            };
            let id = self.manifest.id_at(i);
            let kept = keep[k] as usize + 1;
            let mut changed = false;
            if tile.textures.len() > kept {
                // Over the limit: drop the finer levels now.
                for dropped in tile.textures.drain(kept..) {
                    tile.bytes.textures -= dropped.len() as u64;
                }
                changed = true;
            } else if tile.textures.len() < target as usize + 1
                && tile
                    .undecodable_from
                    .is_none_or(|l| tile.textures.len() < l)
            {
                let next = tile.textures.len() as u32;
                let priority = (frame << 20) | (1 << 19) | (rank as u64).min((1 << 19) - 1);
                if let Some(blob) = tile.texture_blobs.get(next as usize) {
                    fetcher.request_texture(id, next, blob.clone(), priority);
                }
            }
            if changed {
                // The kept levels are on the GPU already: copy them there.
                r.renderer
                    .tiles
                    .coarsen_texture(id, tile.textures.len().min(tile.uploaded_levels) as u32);
                tile.uploaded_levels = tile.uploaded_levels.min(tile.textures.len());
            }
            let decodable = tile
                .textures
                .len()
                .min(tile.undecodable_from.unwrap_or(usize::MAX));
            while tile.uploaded_levels < decodable && uploads < r.config.uploads_per_frame {
                // Only the new level is decoded; the coarser ones are copied on the GPU. If
                // that cannot be done (no level uploaded yet), every level is uploaded.
                let level = tile.uploaded_levels;
                let Some(image) = decode_texture(&tile.textures[level], id, level as u32) else {
                    for dropped in tile.textures.drain(level..) {
                        tile.bytes.textures -= dropped.len() as u64;
                    }
                    tile.undecodable_from = Some(level);
                    break;
                };
                if !r.renderer.tiles.refine_texture(id, level as u32, &image) {
                    let images: Option<Vec<image::RgbaImage>> = tile.textures[..=level]
                        .iter()
                        .enumerate()
                        .map(|(l, b)| decode_texture(b, id, l as u32))
                        .collect();
                    let Some(images) = images else {
                        break;
                    };
                    r.renderer.tiles.upload_texture(id, level as u32, &images);
                }
                tile.uploaded_levels = level + 1;
                uploads += 1;
            }
            tile.bytes.gpu = r.renderer.tiles.tile_bytes(id);
        }
        budget
    }

    /// Bytes that dropping every resident tile's finer texture levels would free (what
    /// [`Scene::shed_textures`] can give back): their encoded bytes, and their GPU texture
    /// past the coarsest level.
    pub(super) fn sheddable_texture_bytes(&self) -> u64 {
        let Some(r) = &self.rendering else {
            return 0;
        };
        let copies = r.renderer.tiles.texture_copies();
        let coarsest =
            copies * coarsest_rgba_bytes(&self.manifest) + r.renderer.tiles.sample_buffer_bytes();
        self.tiles
            .iter()
            .flatten()
            .filter(|t| t.textures.len() > 1)
            .map(|t| {
                t.textures[1..].iter().map(|b| b.len() as u64).sum::<u64>()
                    + t.bytes.gpu.saturating_sub(coarsest)
            })
            .sum()
    }

    /// Drops finer texture levels, least important tiles first, while the scene holds more
    /// than its limit.
    pub(super) fn shed_textures(&mut self) {
        let mut over = self
            .resident_bytes()
            .saturating_sub(self.pager.memory_limit);
        let Some(r) = &mut self.rendering else {
            return;
        };
        if over == 0 {
            return;
        }
        let mut order: Vec<usize> = (0..self.tiles.len())
            .filter(|&i| self.tiles[i].as_ref().is_some_and(|t| t.textures.len() > 1))
            .collect();
        order.sort_by(|&a, &b| r.importance[a].total_cmp(&r.importance[b]).then(b.cmp(&a)));
        for i in order {
            let Some(tile) = &mut self.tiles[i] else {
                continue;
            };
            let id = self.manifest.id_at(i);
            while over > 0 && tile.textures.len() > 1 {
                let before = tile.bytes.total();
                if let Some(dropped) = tile.textures.pop() {
                    tile.bytes.textures -= dropped.len() as u64;
                }
                let keep = tile.textures.len().min(tile.uploaded_levels);
                r.renderer.tiles.coarsen_texture(id, keep as u32);
                tile.uploaded_levels = keep;
                tile.bytes.gpu = r.renderer.tiles.tile_bytes(id);
                over = over.saturating_sub(before.saturating_sub(tile.bytes.total()));
            }
            if over == 0 {
                break;
            }
        }
    }
}

/// Decodes one texture level; a level that does not decode is logged and left out (the
/// tile keeps its coarser texture: its hash was verified, so this is a format the client
/// cannot read, not a transfer error).
pub(super) fn decode_texture(bytes: &[u8], id: TileId, level: u32) -> Option<image::RgbaImage> {
    match image::load_from_memory(bytes) {
        Ok(image) => Some(image.into_rgba8()),
        Err(e) => {
            tracing::warn!(tile = %id, level, error = %e, "texture level does not decode");
            None
        }
    }
}
