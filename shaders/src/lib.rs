//! WGSL shader sources and the `#[repr(C)]` Rust types that mirror each uniform and storage
//! struct they declare, so both sides change together.
//!
//! [`TERRAIN`] draws terrain tiles: `vs_surface` for a tile's strip masks, skirts and planar
//! shadow (told apart by the index, see [`skirt_base`] and [`shadow_base`]), `fs_main` for
//! all of them. Render space is camera-relative:
//! x east, y up, z south, in metres, the camera at the origin (so positions stay precise in
//! `f32` however large the terrain). The tests validate the WGSL with naga, the compiler
//! wgpu uses, and check the layouts below against the shader's.

use bytemuck::{Pod, Zeroable};

/// The terrain shader's WGSL source, reading the sample arena from a storage buffer.
pub const TERRAIN: &str = concat!(
    include_str!("terrain.wgsl"),
    include_str!("samples_buffer.wgsl")
);

/// The same shader reading the sample arena from an integer texture of
/// [`SAMPLE_TEXTURE_WIDTH`] words a row (`R32Uint`, word `k` at column `k %` width, row `k /`
/// width): for backends whose vertex shaders read no storage buffers (WebGL2).
pub const TERRAIN_TEXTURE_SAMPLES: &str = concat!(
    include_str!("terrain.wgsl"),
    include_str!("samples_texture.wgsl")
);

/// Words a row of the sample arena's texture ([`TERRAIN_TEXTURE_SAMPLES`]). Slots follow one
/// another word by word, so the texture's last row holds at most this many words less one
/// that no slot uses (1 KiB); the rows are as many as the device's largest texture side.
pub const SAMPLE_TEXTURE_WIDTH: u32 = 256;

/// The projected grids' WGSL source: persistent grid mapping and the error-bounded
/// projective grid, with its ray-casting pass.
pub const GRID: &str = include_str!("grid.wgsl");
/// The quadtree patches' shader.
pub const PATCHES: &str = include_str!("patches.wgsl");

/// Entry points of [`PATCHES`].
pub mod patch_entry {
    pub const VERTEX: &str = "vs_patch";
    pub const FRAGMENT: &str = "fs_patch";
}

/// Mirror of `Patch` in `patches.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct PatchUniform {
    pub origin: [f32; 4],
    pub spacing: [f32; 4],
    pub uv: [f32; 4],
    pub parent_uv: [f32; 4],
    pub blend: [f32; 4],
}

/// Entry points of [`GRID`].
pub mod grid_entry {
    /// The grid's vertex shader: a vertex of the persistent grid cast onto the terrain.
    pub const GRID: &str = "vs_grid";
    /// Colour only (persistent grid mapping).
    pub const FRAGMENT: &str = "fs_grid";
    /// Colour and the error buffer (the error-bounded projective grid).
    pub const FRAGMENT_ERROR: &str = "fs_grid_error";
    /// A triangle covering the target, for the ray-casting pass.
    pub const FULLSCREEN: &str = "vs_fullscreen";
    /// Ray casting in the pixels the error buffer marks.
    pub const RAY: &str = "fs_ray";
}

/// Flags of [`GridUniform::size`]`[3]`.
pub mod grid_flag {
    /// The grid is warped by the tables of [`super::GridUniform`] (Löffler et al.).
    pub const WARP: u32 = 1;
    /// The grid computes its error and writes the error buffer.
    pub const ERROR_BOUNDED: u32 = 2;
    /// Rays are cast in the pixels the error buffer marks (else they are only counted).
    pub const RAY_CASTING: u32 = 4;
}

/// Grid lines of each warp table of [`GridUniform`].
pub const WARP_LINES: usize = 33;
/// Pyramid levels and slot mips the grid's uniform has room for.
pub const GRID_MAX_LEVELS: usize = 24;
pub const GRID_MAX_MIPS: usize = 16;
/// The mip of a slot whose min/max blocks the ray cast skips through.
pub const RAY_BLOCK_MIP: u32 = 3;
/// What the error buffer holds where no grid triangle was drawn.
pub const ERROR_UNCOVERED: f32 = 2.0;

/// `Grid`, group 1 binding 0 of [`GRID`]: see the shader for each field.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Pod, Zeroable)]
pub struct GridUniform {
    pub forward: [f32; 4],
    pub right: [f32; 4],
    pub up: [f32; 4],
    pub size: [f32; 4],
    pub spacing: [f32; 4],
    pub anchor: [i32; 4],
    pub heights: [f32; 4],
    pub colour: [f32; 4],
    pub screen: [f32; 4],
    pub sky: [f32; 4],
    pub inverse_view_proj: [[f32; 4]; 4],
    pub levels: [[u32; 4]; GRID_MAX_LEVELS],
    pub mips: [[u32; 4]; GRID_MAX_MIPS],
    pub warp_u: [[f32; 4]; 9],
    pub warp_v: [[f32; 4]; 9],
}

/// `SlotInfo` of [`GRID`]: one per slot of the height atlas.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Pod, Zeroable)]
pub struct SlotInfo {
    /// The tile's distance from full resolution, its surface's lowest and highest points.
    pub bounds: [f32; 4],
    /// Column and row in the colour atlas, finest and coarsest colour mips held.
    pub colour: [u32; 4],
}

/// `Counters` of [`GRID`]: pixels whose ray was walked (it enters the terrain's box), pixels
/// the grid covered with an error past the threshold, pixels whose ray hit the terrain, and
/// pixels the error buffer marks (past the threshold, or not covered by the grid).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Pod, Zeroable, Default)]
pub struct GridCounters {
    pub rays: u32,
    pub errors: u32,
    pub hits: u32,
    pub marked: u32,
}

/// Entry points of [`TERRAIN`].
pub mod entry {
    pub const SURFACE: &str = "vs_surface";
    /// The vertex shader of `FRAGMENT_CLIPPED`: `SURFACE` with the position passed on.
    pub const SURFACE_CLIPPED: &str = "vs_clipped";
    pub const FRAGMENT: &str = "fs_main";
    /// The fragment shader that discards what lies past the terrain's edge.
    pub const FRAGMENT_CLIPPED: &str = "fs_clipped";
}

/// Index of the foot of sample 0's skirt, for tiles of `n` samples a side: the foot of
/// sample `i` is `skirt_base(n) + i`.
pub fn skirt_base(n: u32) -> u32 {
    n * n
}

/// Index of the planar shadow's first corner for tiles of `n` samples a side; its four
/// corners (north-west, south-west, north-east, south-east) follow.
pub fn shadow_base(n: u32) -> u32 {
    2 * n * n
}

/// Index of the planar shadow's first band vertex for tiles of `n` samples a side: sample
/// `k` of side `s` (north, east, south, west; `k` west to east or north to south) projected
/// onto the side's plane is `band_base(n) + s * n + k`, its foot on the plane
/// `band_base(n) + 4n + s * n + k`.
pub fn band_base(n: u32) -> u32 {
    2 * n * n + 4
}

/// `Frame`, bind group 0: one per frame.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Pod, Zeroable)]
pub struct FrameUniform {
    /// Camera-relative render space to clip space, column-major (reversed depth).
    pub view_proj: [[f32; 4]; 4],
    /// Unit vector towards the light, render space; `w` unused.
    pub light_dir: [f32; 4],
    /// `x`: ambient share of the light; `y`: a pixel's height per metre of distance along
    /// the view axis (the planar shadow's bands reach that much past a crack's bottom).
    pub params: [f32; 4],
    /// The camera relative to its anchor sample: east, height, south (metres).
    pub camera: [f32; 4],
    /// The terrain's edge in render space: west `x`, north `z`, east `x`, south `z`;
    /// fragments past it are discarded (the padding of the last tiles never shows).
    pub clip: [f32; 4],
}

/// `Tile`: one per drawn tile and frame, per-instance vertex attributes at locations 0 to 8
/// (one per field, `points` four), picked by the draw's first instance.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Pod, Zeroable)]
pub struct TileUniform {
    /// Sample (0, 0) in samples from the camera's anchor sample: `(east, 0, south, 0)`.
    pub origin: [f32; 4],
    /// Metres between samples east and south, samples per side, skirt bottom (metres).
    pub spacing: [f32; 4],
    /// Four points in render space (north-west, south-west, north-east, south-east) that
    /// the indices past the skirts place: the planar shadow's corners, projected onto the
    /// shadow plane by the method; `w` unused.
    pub points: [[f32; 4]; 4],
    /// Where the tile lies in the texture bound with it: `uv = (x, y) + (column, row) /
    /// cells * (z, w)`; `[0, 0, 1, 1]` for its own texture, a part of a MapBlock's otherwise.
    pub uv: [f32; 4],
    /// The tile's first word in the sample words (bind group 1 binding 0), its code base and
    /// its code shift: sample `i`'s height code is `base + (bits_i << shift)`, `bits_i` the
    /// 16 bits of sample `i` (two a word, the even sample in the low half); `w` unused.
    pub codes: [i32; 4],
    /// Metres per code (the quantum) and metres at code 0 (the offset); `z`, `w` unused.
    pub metres: [f32; 4],
}

/// Packs a unit vector as WGSL's `pack4x8snorm(vec4(v, 0))`: component `i` in byte `i`.
pub fn pack_normal(v: [f32; 3]) -> u32 {
    let byte = |x: f32| ((x.clamp(-1.0, 1.0) * 127.0).round() as i8) as u8 as u32;
    byte(v[0]) | byte(v[1]) << 8 | byte(v[2]) << 16
}

#[cfg(test)]
mod tests {
    use super::*;

    fn module() -> naga::Module {
        parse(TERRAIN)
    }

    fn parse(source: &str) -> naga::Module {
        naga::front::wgsl::parse_str(source)
            .unwrap_or_else(|e| panic!("{}", e.emit_to_string(source)))
    }

    fn size_in(module: &naga::Module, name: &str) -> usize {
        let (_, ty) = module
            .types
            .iter()
            .find(|(_, t)| t.name.as_deref() == Some(name))
            .unwrap_or_else(|| panic!("struct {name} is missing"));
        ty.inner.size(module.to_ctx()) as usize
    }

    #[test]
    fn the_grid_shader_parses_validates_and_matches_the_rust_layouts() {
        let module = parse(GRID);
        naga::valid::Validator::new(
            naga::valid::ValidationFlags::all(),
            naga::valid::Capabilities::empty(),
        )
        .validate(&module)
        .unwrap_or_else(|e| panic!("the grid shader validates: {}", e.emit_to_string(GRID)));
        for name in [
            grid_entry::GRID,
            grid_entry::FRAGMENT,
            grid_entry::FRAGMENT_ERROR,
            grid_entry::FULLSCREEN,
            grid_entry::RAY,
        ] {
            assert!(
                module.entry_points.iter().any(|e| e.name == name),
                "entry point {name} is missing"
            );
        }
        assert_eq!(
            size_in(&module, "Frame"),
            size_of_val(&FrameUniform::zeroed())
        );
        assert_eq!(
            size_in(&module, "Grid"),
            size_of_val(&GridUniform::zeroed())
        );
        assert_eq!(
            size_in(&module, "SlotInfo"),
            size_of_val(&SlotInfo::zeroed())
        );
        assert_eq!(
            size_in(&module, "Counters"),
            size_of_val(&GridCounters::zeroed())
        );
        // The constants both sides name.
        for (name, value) in [
            ("FLAG_WARP", grid_flag::WARP.to_string()),
            ("FLAG_ERROR_BOUNDED", grid_flag::ERROR_BOUNDED.to_string()),
            ("FLAG_RAY_CASTING", grid_flag::RAY_CASTING.to_string()),
            ("WARP_LINES", WARP_LINES.to_string()),
            ("BLOCK_MIP", RAY_BLOCK_MIP.to_string()),
        ] {
            assert!(
                GRID.contains(&format!("const {name}: u32 = {value}u;")),
                "{name} is {value} on both sides"
            );
        }
        assert!(GRID.contains(&format!("const UNCOVERED: f32 = {ERROR_UNCOVERED:.1};")));
    }

    const TERRAIN_ENTRIES: [&str; 4] = [
        entry::SURFACE,
        entry::SURFACE_CLIPPED,
        entry::FRAGMENT,
        entry::FRAGMENT_CLIPPED,
    ];

    fn validate(source: &str) -> (naga::Module, naga::valid::ModuleInfo) {
        let module = parse(source);
        let info = naga::valid::Validator::new(
            naga::valid::ValidationFlags::all(),
            naga::valid::Capabilities::empty(),
        )
        .validate(&module)
        .unwrap_or_else(|e| panic!("the terrain shader validates: {}", e.emit_to_string(source)));
        (module, info)
    }

    #[test]
    fn the_terrain_shader_parses_and_validates() {
        for source in [TERRAIN, TERRAIN_TEXTURE_SAMPLES] {
            let (module, _) = validate(source);
            for name in TERRAIN_ENTRIES {
                assert!(
                    module.entry_points.iter().any(|e| e.name == name),
                    "entry point {name} is missing"
                );
            }
        }
        assert!(TERRAIN_TEXTURE_SAMPLES.contains(&format!(
            "const SAMPLE_TEXTURE_WIDTH: u32 = {SAMPLE_TEXTURE_WIDTH}u;"
        )));
    }

    /// GLSL ES 3.00 (WebGL2) of every entry point, or the translator's error.
    fn glsl_es_300(source: &str) -> Result<(), String> {
        let (module, info) = validate(source);
        for ep in &module.entry_points {
            let options = naga::back::glsl::Options {
                version: naga::back::glsl::Version::Embedded {
                    version: 300,
                    is_webgl: true,
                },
                ..Default::default()
            };
            let pipeline = naga::back::glsl::PipelineOptions {
                shader_stage: ep.stage,
                entry_point: ep.name.clone(),
                multiview: None,
            };
            let mut out = String::new();
            naga::back::glsl::Writer::new(
                &mut out,
                &module,
                &info,
                &options,
                &pipeline,
                naga::proc::BoundsCheckPolicies::default(),
            )
            .and_then(|mut w| w.write())
            .map_err(|e| format!("{}: {e}", ep.name))?;
        }
        Ok(())
    }

    /// What WebGL2 runs: the texture-sample variant translates to GLSL ES 3.00 for every
    /// entry point; the storage-buffer one does not (why the variant exists).
    #[test]
    fn the_texture_sample_variant_translates_to_webgl2s_glsl_and_the_storage_one_does_not() {
        glsl_es_300(TERRAIN_TEXTURE_SAMPLES).expect("GLSL ES 3.00 of every entry point");
        let refused = glsl_es_300(TERRAIN).expect_err("no storage buffers in GLSL ES 3.00");
        assert!(refused.contains("STORAGE"), "{refused}");
    }

    #[test]
    fn rust_layouts_match_the_shader() {
        let module = module();
        let size_of = |name: &str| {
            let (_, ty) = module
                .types
                .iter()
                .find(|(_, t)| t.name.as_deref() == Some(name))
                .unwrap_or_else(|| panic!("struct {name} is missing"));
            ty.inner.size(module.to_ctx()) as usize
        };
        assert_eq!(size_of("Frame"), size_of_val(&FrameUniform::zeroed()));
        assert_eq!(size_of("Tile"), size_of_val(&TileUniform::zeroed()));
    }

    #[test]
    fn the_patch_shader_parses_validates_and_matches_the_rust_layout() {
        let module = parse(PATCHES);
        naga::valid::Validator::new(
            naga::valid::ValidationFlags::all(),
            naga::valid::Capabilities::empty(),
        )
        .validate(&module)
        .expect("patches.wgsl validates");
        assert_eq!(size_in(&module, "Patch"), size_of::<PatchUniform>());
        for entry in [patch_entry::VERTEX, patch_entry::FRAGMENT] {
            assert!(
                module.entry_points.iter().any(|e| e.name == entry),
                "{entry}"
            );
        }
    }

    #[test]
    fn normals_pack_as_wgsl_does() {
        assert_eq!(pack_normal([0.0, 1.0, 0.0]), 0x00_7f_00);
        assert_eq!(pack_normal([-1.0, 0.0, 0.0]), 0x81);
        assert_eq!(pack_normal([0.0, 0.0, 2.0]), 0x7f_00_00);
    }
}
