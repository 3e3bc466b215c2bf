//! One request run as a task: its blobs (a tile's heights with its coarsest texture, a
//! finer texture level, a method's data) each tried until it arrives whole or the failure
//! is not worth another try ([`verdict`]), with backoff between tries; what it ended with
//! is the [`FetchEvent`] the fetcher delivers.

use super::{
    Counters, DataSource, FailureKind, FetchEvent, FetcherConfig, Request, Want, backoff_delay, mix,
};
use crate::http_client::{FetchError, FetchedTile, TileClient, decode_tile, verify_hash};
use bytes::Bytes;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;
use terrain_shared::{Manifest, TileId, routes};
use web_time::Instant;

/// What one try of one blob ended with, and what to do next.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Verdict {
    RetryTransient,
    RetryCorrupt,
    GiveUp,
}

/// After try number `tries` of a blob failed with `kind`, `corrupt` of those tries having
/// been corrupt (this one included): try again, or report.
pub(super) fn verdict(
    config: &FetcherConfig,
    kind: FailureKind,
    tries: u32,
    corrupt: u32,
) -> Verdict {
    match kind {
        FailureKind::Transient if tries < config.max_attempts => Verdict::RetryTransient,
        FailureKind::Corrupt
            if corrupt < config.corrupt_attempts && tries < config.max_attempts =>
        {
            Verdict::RetryCorrupt
        }
        _ => Verdict::GiveUp,
    }
}

/// One blob of a request.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Part {
    Heights,
    Texture(u32),
    Data(u32),
}

/// One request, run as a task.
pub(super) struct Job {
    pub(super) client: TileClient,
    pub(super) manifest: Arc<Manifest>,
    pub(super) config: FetcherConfig,
    pub(super) counters: Arc<Counters>,
    pub(super) request: Request,
    /// For [`Want::Data`]: where the body lives.
    pub(super) data: Option<DataSource>,
    /// For [`Want::TextureLevel`]: the hash its body must have.
    pub(super) texture_blob: Option<terrain_shared::Blob>,
    pub(super) jitter_seed: u64,
}

impl Job {
    pub(super) async fn run(&self) -> FetchEvent {
        let Request { id, want } = self.request;
        let started = Instant::now();
        let result = match want {
            Want::Tile => self.tile(started).await,
            Want::TextureLevel(level) => self
                .with_retries(Part::Texture(level), || {
                    self.texture(level, Some(self.texture_blob.as_ref().unwrap_or(&NO_HASH)))
                })
                .await
                .map(|(bytes, _)| FetchEvent::TextureLevel {
                    id,
                    level,
                    bytes,
                    elapsed: started.elapsed(),
                }),
            Want::Data(key) => self
                .with_retries(Part::Data(key), || self.data())
                .await
                .map(|(bytes, _)| FetchEvent::Data { id, key, bytes }),
        };
        result.unwrap_or_else(|(error, attempts)| {
            tracing::debug!(tile = %id, ?want, attempts, %error, "giving up");
            FetchEvent::Failed {
                id,
                want,
                error,
                attempts,
            }
        })
    }

    /// The tile blob and the coarsest texture level, fetched side by side: one after the
    /// other, a tile took two round trips, and on a slow link (2 s a request) the viewpoint
    /// had moved on before it landed. The texture's hash is in the tile blob, so it is
    /// checked when both are in; a texture that fails is fetched again, verified.
    async fn tile(&self, started: Instant) -> Result<FetchEvent, (FetchError, u32)> {
        let (((tile, heights_bytes, decode), heights_tries), (texture, texture_tries)) = tokio::try_join!(
            self.with_retries(Part::Heights, || self.heights()),
            self.with_retries(Part::Texture(0), || self.texture(0, None)),
        )?;
        let Some(coarsest) = tile.texture.first() else {
            return Err((
                FetchError::NoSuchTextureLevel {
                    id: self.request.id,
                    level: 0,
                    levels: 0,
                },
                heights_tries,
            ));
        };
        let url = self.client.url(&routes::texture(
            &self.manifest.content_version,
            self.request.id,
            0,
        ));
        let (coarsest_texture, texture_tries) = match verify_hash(&url, &texture, &coarsest.hash) {
            Ok(()) => (texture, texture_tries),
            Err(error) => {
                self.counters
                    .corrupt_refetches
                    .fetch_add(1, Ordering::Relaxed);
                tracing::debug!(tile = %self.request.id, %error, "coarsest texture refetched");
                let (texture, tries) = self
                    .with_retries(Part::Texture(0), || self.texture(0, Some(coarsest)))
                    .await?;
                (texture, texture_tries + tries)
            }
        };
        Ok(FetchEvent::Tile {
            id: self.request.id,
            heights: tile.heights,
            heights_bytes,
            mask_errors_m: tile.mask_errors_m,
            texture: tile.texture,
            coarsest_texture,
            attempts: heights_tries.max(texture_tries),
            elapsed: started.elapsed(),
            decode,
        })
    }

    /// One blob with its retries: the blob and the tries it took, or the last error and
    /// the tries made.
    async fn with_retries<T, F, Try>(
        &self,
        part: Part,
        mut try_once: F,
    ) -> Result<(T, u32), (FetchError, u32)>
    where
        F: FnMut() -> Try,
        Try: Future<Output = Result<T, FetchError>>,
    {
        let mut tries = 0;
        let mut corrupt = 0;
        loop {
            tries += 1;
            let error = match try_once().await {
                Ok(fetched) => return Ok((fetched, tries)),
                Err(error) => error,
            };
            let kind = FailureKind::of(&error);
            if kind == FailureKind::Corrupt {
                corrupt += 1;
            }
            let counter = match verdict(&self.config, kind, tries, corrupt) {
                Verdict::GiveUp => return Err((error, tries)),
                Verdict::RetryTransient => &self.counters.retries,
                Verdict::RetryCorrupt => &self.counters.corrupt_refetches,
            };
            counter.fetch_add(1, Ordering::Relaxed);
            let random = mix(self.jitter_seed ^ mix(u64::from(tries)) ^ part_salt(part));
            let delay = backoff_delay(&self.config, tries - 1, random);
            tracing::debug!(
                tile = %self.request.id, ?part, tries, ?kind, %error,
                delay_ms = delay.as_millis() as u64, "retrying"
            );
            crate::tasks::sleep(delay).await;
        }
    }

    /// One try of the tile blob: fetched, verified, decoded; with its size.
    async fn heights(&self) -> Result<(FetchedTile, u64, Duration), FetchError> {
        let (manifest, id) = (&*self.manifest, self.request.id);
        let body = self
            .counted(Part::Heights, self.client.tile_bytes(manifest, id))
            .await?;
        let bytes = body.len() as u64;
        let url = self
            .client
            .url(&routes::heights(&manifest.content_version, id));
        let decoding = Instant::now();
        let tile = decode_tile(url, body).await?;
        Ok((tile, bytes, decoding.elapsed()))
    }

    /// One try of a texture level: fetched, and verified against `expected` when given.
    async fn texture(
        &self,
        level: u32,
        expected: Option<&terrain_shared::Blob>,
    ) -> Result<Bytes, FetchError> {
        let (manifest, id) = (&*self.manifest, self.request.id);
        self.counted(
            Part::Texture(level),
            self.client.texture(manifest, id, level, expected),
        )
        .await
    }

    /// One try of a method's data: fetched, and verified when its hash is known.
    async fn data(&self) -> Result<Bytes, FetchError> {
        let Some(source) = &self.data else {
            return Err(FetchError::Cancelled {
                url: format!("data of tile {} with no source", self.request.id),
            });
        };
        let part = match self.request.want {
            Want::Data(key) => Part::Data(key),
            _ => Part::Heights,
        };
        self.counted(
            part,
            self.client
                .blob(&source.path, source.hash.as_deref(), source.bytes),
        )
        .await
    }

    /// Runs one GET of `part`, counting the request and the body.
    async fn counted(
        &self,
        part: Part,
        get: impl Future<Output = Result<Bytes, FetchError>>,
    ) -> Result<Bytes, FetchError> {
        // Refusals that need no request (not in the grid, no such level) come back here
        // as they would from the client, before anything is counted.
        let expected = expected_bytes(
            &self.manifest,
            self.request.id,
            part,
            self.texture_blob.as_ref(),
        )?;
        self.counters
            .requests_started
            .fetch_add(1, Ordering::Relaxed);
        let result = get.await;
        let received = match &result {
            Ok(body) => body.len() as u64,
            Err(FetchError::HashMismatch { .. }) => expected,
            Err(_) => 0,
        };
        self.counters
            .bytes_downloaded
            .fetch_add(received, Ordering::Relaxed);
        result
    }
}

/// A texture request made without its hash ([`Fetcher::request`] rather than
/// [`Fetcher::request_texture`]): no body matches it, so it fails as corrupt, never passes.
pub(super) static NO_HASH: terrain_shared::Blob = terrain_shared::Blob {
    hash: String::new(),
    bytes: 0,
};

/// The known size of a blob, or the error [`TileClient`] would give without a request.
pub(super) fn expected_bytes(
    manifest: &Manifest,
    id: TileId,
    part: Part,
    texture: Option<&terrain_shared::Blob>,
) -> Result<u64, FetchError> {
    let record = manifest.tile(id).ok_or_else(|| {
        let grid = manifest.grid(id.level);
        FetchError::NotInGrid {
            id,
            columns: grid.columns,
            rows: grid.rows,
        }
    })?;
    match part {
        Part::Heights => Ok(record.bytes),
        Part::Texture(level) if level >= manifest.texture.levels => {
            Err(FetchError::NoSuchTextureLevel {
                id,
                level,
                levels: manifest.texture.levels,
            })
        }
        // The coarsest level's size is known once the tile blob is in.
        Part::Texture(_) => Ok(texture.map_or(0, |b| b.bytes)),
        // The manifest does not know a method's data.
        Part::Data(_) => Ok(0),
    }
}

pub(super) fn part_salt(part: Part) -> u64 {
    match part {
        Part::Heights => 0,
        Part::Texture(level) => mix(u64::from(level) + 1),
        Part::Data(key) => mix(u64::from(key) ^ 0xDA7A),
    }
}
