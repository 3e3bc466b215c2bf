//! An offscreen colour target and its read-back into an image.

use super::gpu::{Gpu, GpuError};

/// Format of offscreen targets: 8-bit sRGB, as PNG frames are stored.
pub const OFFSCREEN_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8UnormSrgb;

/// A colour texture to render into and read back.
#[derive(Debug)]
pub struct Offscreen {
    pub texture: wgpu::Texture,
    pub view: wgpu::TextureView,
}

impl Offscreen {
    pub fn new(gpu: &Gpu, width: u32, height: u32) -> Offscreen {
        let texture = gpu.device.create_texture(&wgpu::TextureDescriptor {
            label: Some("offscreen"),
            size: wgpu::Extent3d {
                width,
                height,
                depth_or_array_layers: 1,
            },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: OFFSCREEN_FORMAT,
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC,
            view_formats: &[],
        });
        let view = texture.create_view(&Default::default());
        Offscreen { texture, view }
    }

    /// The target's pixels, waiting for the GPU.
    pub fn read(&self, gpu: &Gpu) -> Result<image::RgbaImage, GpuError> {
        let (width, height) = (self.texture.width(), self.texture.height());
        let pixels = read_texture(&gpu.device, &gpu.queue, &self.texture, 4)?;
        image::RgbaImage::from_raw(width, height, pixels)
            .ok_or_else(|| GpuError::Readback("short read-back".into()))
    }
}

/// Mip 0 of `texture` (every aspect, `bytes_per_texel` bytes a texel), row after row with
/// no padding, waiting (at most [`super::gpu::GPU_TIMEOUT`]) for the GPU.
pub fn read_texture(
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    texture: &wgpu::Texture,
    bytes_per_texel: u32,
) -> Result<Vec<u8>, GpuError> {
    let (width, height) = (texture.width(), texture.height());
    // Rows of a buffer copy are aligned to 256 bytes.
    let tight = bytes_per_texel * width;
    let row =
        tight.div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT) * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
    let buffer = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("readback"),
        size: u64::from(row) * u64::from(height),
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let aspect = if texture.format().is_depth_stencil_format() {
        wgpu::TextureAspect::DepthOnly
    } else {
        wgpu::TextureAspect::All
    };
    let mut encoder = device.create_command_encoder(&Default::default());
    encoder.copy_texture_to_buffer(
        wgpu::TexelCopyTextureInfo {
            texture,
            mip_level: 0,
            origin: wgpu::Origin3d::ZERO,
            aspect,
        },
        wgpu::TexelCopyBufferInfo {
            buffer: &buffer,
            layout: wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(row),
                rows_per_image: Some(height),
            },
        },
        texture.size(),
    );
    queue.submit([encoder.finish()]);
    let slice = buffer.slice(..);
    slice.map_async(wgpu::MapMode::Read, |_| {});
    // An image read back must be finished: this waits, bounded (a lost GPU is an error).
    device
        .poll(wgpu::PollType::Wait {
            submission_index: None,
            timeout: Some(super::gpu::GPU_TIMEOUT),
        })
        .map_err(|e| GpuError::Readback(format!("waiting for the GPU: {e}")))?;
    let data = slice
        .get_mapped_range()
        .map_err(|e| GpuError::Readback(e.to_string()))?;
    let mut bytes = Vec::with_capacity((tight * height) as usize);
    for y in 0..height as usize {
        let start = y * row as usize;
        bytes.extend_from_slice(&data[start..start + tight as usize]);
    }
    drop(data);
    buffer.unmap();
    Ok(bytes)
}
