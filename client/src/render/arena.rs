//! The sample arena's storage ([`super::tiles`]): the words of every drawn tile's samples,
//! slot after slot, in one storage buffer, or, where vertex shaders read no storage buffers
//! (WebGL2, [`SampleStore::Texture`]), in one `R32Uint` texture of
//! [`SAMPLE_TEXTURE_WIDTH`] words a row. Word `k` of the arena is the same word either way,
//! so a tile's first word and the shader's arithmetic do not change with the store.

use super::gpu::SampleStore;
use terrain_shaders::SAMPLE_TEXTURE_WIDTH;

/// Labels of the arena's allocation.
pub mod label {
    pub const SAMPLES: &str = "terrain/sample arena";
    /// The arena while it holds no slot: a 4-byte buffer (one row of texture) so that its
    /// binding is never empty, part of the renderer's fixed cost, not the terrain's.
    pub const EMPTY_SAMPLES: &str = "empty sample arena";
}

/// The terrain shader that reads the arena from `kind`.
pub(super) fn terrain_shader(kind: SampleStore) -> &'static str {
    match kind {
        SampleStore::Buffer => terrain_shaders::TERRAIN,
        SampleStore::Texture => terrain_shaders::TERRAIN_TEXTURE_SAMPLES,
    }
}

#[derive(Debug)]
enum Store {
    Buffer(wgpu::Buffer),
    Texture {
        texture: wgpu::Texture,
        view: wgpu::TextureView,
    },
}

/// The sample arena: `slots` slots of `slot_words` words.
#[derive(Debug)]
pub(super) struct Arena {
    store: Store,
    pub(super) slots: u32,
    slot_words: u64,
    /// Changes whenever the storage does, so that bind groups holding it are made again.
    pub(super) generation: u64,
}

impl Arena {
    /// An arena of `slots` slots of `slot_words` words (contents undefined).
    pub(super) fn new(
        device: &wgpu::Device,
        kind: SampleStore,
        slots: u32,
        slot_words: u64,
        generation: u64,
    ) -> Arena {
        let label = Some(if slots == 0 {
            label::EMPTY_SAMPLES
        } else {
            label::SAMPLES
        });
        let words = u64::from(slots) * slot_words;
        let store = match kind {
            SampleStore::Buffer => Store::Buffer(device.create_buffer(&wgpu::BufferDescriptor {
                label,
                size: (4 * words).max(4),
                usage: wgpu::BufferUsages::STORAGE
                    | wgpu::BufferUsages::COPY_DST
                    | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            })),
            SampleStore::Texture => {
                let texture = device.create_texture(&wgpu::TextureDescriptor {
                    label,
                    size: wgpu::Extent3d {
                        width: SAMPLE_TEXTURE_WIDTH,
                        height: rows(words).max(1),
                        depth_or_array_layers: 1,
                    },
                    mip_level_count: 1,
                    sample_count: 1,
                    dimension: wgpu::TextureDimension::D2,
                    format: wgpu::TextureFormat::R32Uint,
                    usage: wgpu::TextureUsages::TEXTURE_BINDING
                        | wgpu::TextureUsages::COPY_DST
                        | wgpu::TextureUsages::COPY_SRC,
                    view_formats: &[],
                });
                let view = texture.create_view(&Default::default());
                Store::Texture { texture, view }
            }
        };
        Arena {
            store,
            slots,
            slot_words,
            generation,
        }
    }

    /// The most slots of `slot_words` words one arena of `kind` holds on a device of
    /// `limits`: one storage binding and one buffer, or one texture.
    pub(super) fn max_slots(kind: SampleStore, limits: &wgpu::Limits, slot_words: u64) -> u32 {
        let words = match kind {
            SampleStore::Buffer => {
                limits
                    .max_storage_buffer_binding_size
                    .min(limits.max_buffer_size)
                    / 4
            }
            SampleStore::Texture => {
                u64::from(SAMPLE_TEXTURE_WIDTH) * u64::from(limits.max_texture_dimension_2d)
            }
        };
        u32::try_from(words / slot_words.max(1))
            .unwrap_or(u32::MAX)
            .max(1)
    }

    /// The group-1 layout entry the terrain shader of `kind` reads the arena through.
    pub(super) fn layout_entry(kind: SampleStore) -> wgpu::BindGroupLayoutEntry {
        let ty = match kind {
            SampleStore::Buffer => wgpu::BindingType::Buffer {
                ty: wgpu::BufferBindingType::Storage { read_only: true },
                has_dynamic_offset: false,
                min_binding_size: wgpu::BufferSize::new(4),
            },
            SampleStore::Texture => wgpu::BindingType::Texture {
                sample_type: wgpu::TextureSampleType::Uint,
                view_dimension: wgpu::TextureViewDimension::D2,
                multisampled: false,
            },
        };
        wgpu::BindGroupLayoutEntry {
            binding: 0,
            visibility: wgpu::ShaderStages::VERTEX,
            ty,
            count: None,
        }
    }

    /// What group 1 binds.
    pub(super) fn binding(&self) -> wgpu::BindingResource<'_> {
        match &self.store {
            Store::Buffer(buffer) => buffer.as_entire_binding(),
            Store::Texture { view, .. } => wgpu::BindingResource::TextureView(view),
        }
    }

    /// Bytes it holds for its slots (0 while it has none): the texture's whole rows, so up
    /// to [`SAMPLE_TEXTURE_WIDTH`] words less one more than the slots' words.
    pub(super) fn bytes(&self) -> u64 {
        let words = u64::from(self.slots) * self.slot_words;
        match (&self.store, self.slots) {
            (_, 0) => 0,
            (Store::Buffer(_), _) => 4 * words,
            (Store::Texture { .. }, _) => {
                4 * u64::from(rows(words)) * u64::from(SAMPLE_TEXTURE_WIDTH)
            }
        }
    }

    /// Writes `words` (at most a slot's) into slot `position`.
    pub(super) fn write(&self, queue: &wgpu::Queue, position: u32, words: &[u32]) {
        let first = u64::from(position) * self.slot_words;
        match &self.store {
            Store::Buffer(buffer) => {
                queue.write_buffer(buffer, 4 * first, bytemuck::cast_slice(words));
            }
            Store::Texture { texture, .. } => {
                for run in runs(first, first, words.len() as u64) {
                    let at = (run.from - first) as usize;
                    queue.write_texture(
                        texel(texture, run.to),
                        bytemuck::cast_slice(&words[at..at + run.len as usize]),
                        wgpu::TexelCopyBufferLayout {
                            offset: 0,
                            bytes_per_row: None,
                            rows_per_image: None,
                        },
                        row_extent(run.len),
                    );
                }
            }
        }
    }

    /// Copies slot `from` of this arena into slot `to` of `into` (of the same store and
    /// slot size), on the GPU.
    pub(super) fn copy_slot(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        from: u32,
        into: &Arena,
        to: u32,
    ) {
        let (src, dst) = (
            u64::from(from) * self.slot_words,
            u64::from(to) * into.slot_words,
        );
        match (&self.store, &into.store) {
            (Store::Buffer(old), Store::Buffer(new)) => {
                encoder.copy_buffer_to_buffer(old, 4 * src, new, 4 * dst, 4 * self.slot_words);
            }
            (Store::Texture { texture: old, .. }, Store::Texture { texture: new, .. }) => {
                for run in runs(src, dst, self.slot_words) {
                    encoder.copy_texture_to_texture(
                        texel(old, run.from),
                        texel(new, run.to),
                        row_extent(run.len),
                    );
                }
            }
            _ => unreachable!("an arena is copied into one of the same store"),
        }
    }
}

/// Texture rows holding `words` words.
fn rows(words: u64) -> u32 {
    u32::try_from(words.div_ceil(u64::from(SAMPLE_TEXTURE_WIDTH))).unwrap_or(u32::MAX)
}

/// A run of words that lies within one texture row at both ends of a copy.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Run {
    from: u64,
    to: u64,
    len: u64,
}

/// `len` words from word `from` to word `to`, cut where either side crosses a row.
fn runs(mut from: u64, mut to: u64, len: u64) -> Vec<Run> {
    let width = u64::from(SAMPLE_TEXTURE_WIDTH);
    let mut left = len;
    let mut out = Vec::new();
    while left > 0 {
        let n = left.min(width - from % width).min(width - to % width);
        out.push(Run { from, to, len: n });
        from += n;
        to += n;
        left -= n;
    }
    out
}

fn texel(texture: &wgpu::Texture, word: u64) -> wgpu::TexelCopyTextureInfo<'_> {
    let width = u64::from(SAMPLE_TEXTURE_WIDTH);
    wgpu::TexelCopyTextureInfo {
        texture,
        mip_level: 0,
        origin: wgpu::Origin3d {
            x: (word % width) as u32,
            y: (word / width) as u32,
            z: 0,
        },
        aspect: wgpu::TextureAspect::All,
    }
}

fn row_extent(len: u64) -> wgpu::Extent3d {
    wgpu::Extent3d {
        width: len as u32,
        height: 1,
        depth_or_array_layers: 1,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn runs_cover_every_word_once_and_never_cross_a_row() {
        let width = u64::from(SAMPLE_TEXTURE_WIDTH);
        for (from, to, len) in [
            (0, 0, 0),
            (0, 0, 2113),
            (2113, 0, 2113),
            (5, width - 1, 3 * width + 7),
            (width, 2 * width, width),
        ] {
            let got = runs(from, to, len);
            assert_eq!(got.iter().map(|r| r.len).sum::<u64>(), len);
            let mut next = (from, to);
            for r in &got {
                assert_eq!((r.from, r.to), next, "contiguous");
                assert!(r.len > 0);
                assert_eq!(r.from / width, (r.from + r.len - 1) / width, "{r:?}");
                assert_eq!(r.to / width, (r.to + r.len - 1) / width, "{r:?}");
                next = (r.from + r.len, r.to + r.len);
            }
        }
        assert_eq!(
            runs(0, 0, 2 * width),
            vec![
                Run {
                    from: 0,
                    to: 0,
                    len: width
                },
                Run {
                    from: width,
                    to: width,
                    len: width
                }
            ]
        );
    }

    #[test]
    fn a_texture_arena_holds_whole_rows_and_at_most_its_device_side_of_them() {
        let limits = wgpu::Limits::downlevel_webgl2_defaults();
        let words = 2113;
        assert_eq!(
            Arena::max_slots(SampleStore::Texture, &limits, words),
            (256 * 2048 / 2113) as u32
        );
        assert_eq!(rows(0), 0);
        assert_eq!(rows(1), 1);
        assert_eq!(rows(256), 1);
        assert_eq!(rows(257), 2);
    }
}
