//! The wgpu adapter and device, headless or for a window.
//!
//! `REQUIRE_GPU=1` (CI sets it) turns "no adapter" into an error and insists on a Vulkan
//! adapter: wgpu's GL fallback draws strips wrongly, so a run that silently fell back to it
//! would test nothing. Without the variable, the backends come from `WGPU_BACKEND` (all
//! native backends when unset).

use thiserror::Error;
pub use wgpu::Backend;

/// The longest any wait for the GPU lasts: past it the GPU is taken as lost (an error, not a
/// hang).
pub const GPU_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(30);

/// Set to 1 to require a Vulkan adapter (and fail without one).
pub const REQUIRE_GPU_VAR: &str = "REQUIRE_GPU";

#[derive(Debug, Error)]
pub enum GpuError {
    #[error(
        "no graphics adapter: {0}. On a machine without a GPU install Mesa's software Vulkan driver \
         (Debian/Ubuntu: apt-get install mesa-vulkan-drivers libvulkan1) and set WGPU_BACKEND=vulkan"
    )]
    NoAdapter(String),
    #[error("the adapter {adapter} refused a device: {message}")]
    Device { adapter: String, message: String },
    #[error("{REQUIRE_GPU_VAR}=1 needs a Vulkan adapter, but wgpu chose {0}")]
    NotVulkan(String),
    #[error("cannot read the frame back from the GPU: {0}")]
    Readback(String),
    #[error("cannot create a surface for the window: {0}")]
    Surface(String),
}

/// An adapter, its device and queue.
#[derive(Debug, Clone)]
pub struct Gpu {
    pub instance: wgpu::Instance,
    pub adapter: wgpu::Adapter,
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    /// Where the terrain's vertex shader reads the tiles' samples from.
    pub samples: SampleStore,
}

/// Where the terrain's vertex shader reads the tiles' samples (the sample arena,
/// [`super::tiles`]) from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SampleStore {
    /// A storage buffer (`terrain_shaders::TERRAIN`): every backend with storage buffers in
    /// vertex shaders.
    Buffer,
    /// An `R32Uint` texture of `terrain_shaders::SAMPLE_TEXTURE_WIDTH` words a row
    /// (`terrain_shaders::TERRAIN_TEXTURE_SAMPLES`): WebGL2, whose vertex shaders read no
    /// storage buffers. The same words at the same indices, so frames are the same.
    Texture,
}

/// Whether `REQUIRE_GPU=1` is set.
pub fn gpu_required() -> bool {
    std::env::var(REQUIRE_GPU_VAR).is_ok_and(|v| v == "1")
}

impl Gpu {
    /// A device for offscreen rendering.
    #[cfg(not(target_arch = "wasm32"))]
    pub fn headless() -> Result<Gpu, GpuError> {
        Self::headless_with(gpu_required())
    }

    /// A device for offscreen rendering; with `require_vulkan`, a Vulkan one or an error
    /// (what `REQUIRE_GPU=1` asks for).
    #[cfg(not(target_arch = "wasm32"))]
    pub fn headless_with(require_vulkan: bool) -> Result<Gpu, GpuError> {
        Self::open(Self::instance_with(require_vulkan), None, require_vulkan)
    }

    /// The instance every device of this program comes from: backends from `WGPU_BACKEND`,
    /// Vulkan only when `REQUIRE_GPU=1`.
    pub fn instance() -> wgpu::Instance {
        Self::instance_with(gpu_required())
    }

    fn instance_with(require_vulkan: bool) -> wgpu::Instance {
        let mut descriptor = wgpu::InstanceDescriptor::new_without_display_handle_from_env();
        if require_vulkan {
            descriptor.backends = wgpu::Backends::VULKAN;
        }
        wgpu::Instance::new(descriptor)
    }

    /// A device from `instance` able to present to `surface`, when given.
    #[cfg(not(target_arch = "wasm32"))]
    pub fn with_instance(
        instance: wgpu::Instance,
        surface: Option<&wgpu::Surface<'_>>,
    ) -> Result<Gpu, GpuError> {
        Self::open(instance, surface, gpu_required())
    }

    #[cfg(not(target_arch = "wasm32"))]
    fn open(
        instance: wgpu::Instance,
        surface: Option<&wgpu::Surface<'_>>,
        require_vulkan: bool,
    ) -> Result<Gpu, GpuError> {
        pollster::block_on(Self::request(instance, surface, require_vulkan))
    }

    /// A device of the page's WebGPU able to
    /// present to `surface`, a canvas's.
    #[cfg(target_arch = "wasm32")]
    pub async fn for_page(
        instance: wgpu::Instance,
        surface: &wgpu::Surface<'_>,
    ) -> Result<Gpu, GpuError> {
        Self::request(instance, Some(surface), false).await
    }

    async fn request(
        instance: wgpu::Instance,
        surface: Option<&wgpu::Surface<'_>>,
        require_vulkan: bool,
    ) -> Result<Gpu, GpuError> {
        let adapter = instance
            .request_adapter(&wgpu::RequestAdapterOptions {
                power_preference: wgpu::PowerPreference::HighPerformance,
                force_fallback_adapter: false,
                compatible_surface: surface,
                apply_limit_buckets: false,
            })
            .await
            .map_err(|e| GpuError::NoAdapter(e.to_string()))?;
        let info = adapter.get_info();
        if require_vulkan && info.backend != wgpu::Backend::Vulkan {
            return Err(GpuError::NotVulkan(describe(&info)));
        }
        let downlevel = adapter.get_downlevel_capabilities().flags;
        let samples = if downlevel.contains(wgpu::DownlevelFlags::VERTEX_STORAGE) {
            SampleStore::Buffer
        } else {
            SampleStore::Texture
        };
        // Timestamps measure the GPU's share of a frame; adapters without them still render.
        let required_features = adapter.features() & wgpu::Features::TIMESTAMP_QUERY;
        // The adapter's own texture sizes and buffer sizes: the sample arena and the grids'
        // atlas hold every drawn tile in one buffer, as large as the adapter allows.
        // A downlevel adapter (WebGL2) gets its own floor of limits: the default ones ask for
        // storage buffers and compute shaders it lacks.
        let available = adapter.limits();
        let floor = if downlevel.contains(wgpu::DownlevelFlags::COMPUTE_SHADERS) {
            wgpu::Limits::default()
        } else {
            wgpu::Limits::downlevel_webgl2_defaults()
        };
        let required_limits = wgpu::Limits {
            max_storage_buffer_binding_size: available.max_storage_buffer_binding_size,
            max_buffer_size: available.max_buffer_size,
            ..floor.using_resolution(available)
        };
        let (device, queue) = adapter
            .request_device(&wgpu::DeviceDescriptor {
                label: Some("terrain"),
                required_features,
                required_limits,
                ..Default::default()
            })
            .await
            .map_err(|e| GpuError::Device {
                adapter: describe(&info),
                message: e.to_string(),
            })?;
        Ok(Gpu {
            instance,
            adapter,
            device,
            queue,
            samples,
        })
    }

    /// This device reading the tiles' samples from `store`: the texture on a device that has
    /// storage buffers too, to compare the two paths on one adapter (the tests do).
    pub fn with_samples(mut self, store: SampleStore) -> Gpu {
        if store == SampleStore::Buffer {
            assert!(
                self.downlevel()
                    .contains(wgpu::DownlevelFlags::VERTEX_STORAGE),
                "{} has no storage buffers in vertex shaders",
                self.description()
            );
        }
        self.samples = store;
        self
    }

    /// What the adapter has of what WebGPU's full profile needs (WebGL2 lacks some).
    pub fn downlevel(&self) -> wgpu::DownlevelFlags {
        self.adapter.get_downlevel_capabilities().flags
    }

    /// "llvmpipe (LLVM 15.0.6, 256 bits), Vulkan, Cpu": what a benchmark names it ran on.
    pub fn description(&self) -> String {
        describe(&self.adapter.get_info())
    }

    /// Whether GPU frame times can be measured.
    pub fn has_timestamps(&self) -> bool {
        self.device
            .features()
            .contains(wgpu::Features::TIMESTAMP_QUERY)
    }

    /// How `surface` (a window's or a canvas's) is configured for frames of `width` x
    /// `height`, and the format of the views frames are drawn through: sRGB, as the
    /// offscreen frames are (the shader writes linear colour); a surface whose own formats
    /// are not sRGB (a canvas's) gets sRGB views. `None` when this adapter cannot present
    /// to it.
    pub fn surface_config(
        &self,
        surface: &wgpu::Surface<'_>,
        width: u32,
        height: u32,
    ) -> Option<(wgpu::SurfaceConfiguration, wgpu::TextureFormat)> {
        let capabilities = surface.get_capabilities(&self.adapter);
        let mut config = surface.get_default_config(&self.adapter, width.max(1), height.max(1))?;
        config.format = capabilities
            .formats
            .iter()
            .copied()
            .find(wgpu::TextureFormat::is_srgb)
            .unwrap_or(config.format);
        let view_format = config.format.add_srgb_suffix();
        if view_format != config.format {
            config.view_formats = vec![view_format];
        }
        Some((config, view_format))
    }

    /// Largest texture side the device accepts.
    pub fn max_texture_side(&self) -> u32 {
        self.device.limits().max_texture_dimension_2d
    }
}

fn describe(info: &wgpu::AdapterInfo) -> String {
    format!("{}, {:?}, {:?}", info.name, info.backend, info.device_type)
}
