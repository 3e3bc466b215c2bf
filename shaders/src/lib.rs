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

/// The terrain shader's WGSL source.
pub const TERRAIN: &str = include_str!("terrain.wgsl");

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

/// `Frame`, bind group 0: one per frame.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Pod, Zeroable)]
pub struct FrameUniform {
    /// Camera-relative render space to clip space, column-major (reversed depth).
    pub view_proj: [[f32; 4]; 4],
    /// Unit vector towards the light, render space; `w` unused.
    pub light_dir: [f32; 4],
    /// `x`: ambient share of the light.
    pub params: [f32; 4],
    /// The camera relative to its anchor sample: east, height, south (metres).
    pub camera: [f32; 4],
    /// The terrain's edge in render space: west `x`, north `z`, east `x`, south `z`;
    /// fragments past it are discarded (the padding of the last tiles never shows).
    pub clip: [f32; 4],
}

/// `Tile`, bind group 1: one per drawn tile and frame, at a dynamic offset.
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
}

/// One sample of a tile in its storage buffer, bind group 2 (its texture is group 3).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Pod, Zeroable)]
pub struct Sample {
    /// Metres above the datum.
    pub height: f32,
    /// Unit normal in render space, packed as WGSL's `pack4x8snorm`.
    pub normal: u32,
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
        naga::front::wgsl::parse_str(TERRAIN)
            .unwrap_or_else(|e| panic!("{}", e.emit_to_string(TERRAIN)))
    }

    #[test]
    fn the_terrain_shader_parses_and_validates() {
        let module = module();
        naga::valid::Validator::new(
            naga::valid::ValidationFlags::all(),
            naga::valid::Capabilities::empty(),
        )
        .validate(&module)
        .expect("the terrain shader validates");
        for name in [
            entry::SURFACE,
            entry::SURFACE_CLIPPED,
            entry::FRAGMENT,
            entry::FRAGMENT_CLIPPED,
        ] {
            assert!(
                module.entry_points.iter().any(|e| e.name == name),
                "entry point {name} is missing"
            );
        }
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
        assert_eq!(size_of("Sample"), size_of_val(&Sample::zeroed()));
    }

    #[test]
    fn normals_pack_as_wgsl_does() {
        assert_eq!(pack_normal([0.0, 1.0, 0.0]), 0x00_7f_00);
        assert_eq!(pack_normal([-1.0, 0.0, 0.0]), 0x81);
        assert_eq!(pack_normal([0.0, 0.0, 2.0]), 0x7f_00_00);
    }
}
