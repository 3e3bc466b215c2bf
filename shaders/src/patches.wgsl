// Quadtree progressive patches (Yusov and Turlapov 2007): one draw per patch of its cached
// triangulation, geomorphed towards its parent patch's over the morph parameter, its
// texture blended with its parent tile's (the paper's texture morphing, figure 10's
// neighbour weights computed here rather than read from a texture). The Rust mirror of
// `Patch` is `PatchUniform` in src/lib.rs.

struct Frame {
    view_proj: mat4x4<f32>,
    light_dir: vec4<f32>,
    params: vec4<f32>,
    camera: vec4<f32>,
    clip: vec4<f32>,
};

struct Patch {
    // x, y: the patch's origin (patch unit 0) as level-0 samples relative to the camera's
    // anchor sample; z: level-0 samples per patch unit; w: metres the flanges hang down.
    origin: vec4<f32>,
    // x, y: metres between level-0 samples east and south; z: the morph parameter (0: its
    // own triangulation, 1: its parent's); w: unused.
    spacing: vec4<f32>,
    // Texture coordinates of patch point p: own tile p * x + (y, z); parent tile
    // p * w + parent.xy.
    uv: vec4<f32>,
    parent_uv: vec4<f32>,
    // Texture blend with each neighbour (west, east, north, south) at the shared side.
    blend: vec4<f32>,
};

@group(0) @binding(0) var<uniform> frame: Frame;
@group(1) @binding(0) var<uniform> piece: Patch;
@group(1) @binding(1) var own_texture: texture_2d<f32>;
@group(1) @binding(2) var parent_texture: texture_2d<f32>;
@group(1) @binding(3) var patch_sampler: sampler;

struct Vertex {
    // Position in patch units and height (metres), then the same of its morph target.
    @location(0) own: vec3<f32>,
    @location(1) goal: vec3<f32>,
    // 1 for the foot of a flange.
    @location(2) flange: f32,
    // Unit normal, render space: its own triangles', area-weighted.
    @location(3) normal: vec4<f32>,
};

struct Varyings {
    @builtin(position) clip: vec4<f32>,
    @location(0) local: vec2<f32>,
    @location(1) position: vec3<f32>,
    @location(2) normal: vec3<f32>,
};

@vertex
fn vs_patch(v: Vertex) -> Varyings {
    let p = mix(v.own, v.goal, piece.spacing.z);
    let sample = piece.origin.xy + p.xy * piece.origin.z;
    let height = p.z - v.flange * piece.origin.w;
    let position = vec3<f32>(
        sample.x * piece.spacing.x - frame.camera.x,
        height - frame.camera.y,
        sample.y * piece.spacing.y - frame.camera.z,
    );
    var out: Varyings;
    out.clip = frame.view_proj * vec4<f32>(position, 1.0);
    out.local = p.xy;
    out.position = position;
    out.normal = v.normal.xyz;
    return out;
}

@fragment
fn fs_patch(in: Varyings) -> @location(0) vec4<f32> {
    if in.position.x < frame.clip.x || in.position.z < frame.clip.y || in.position.x > frame.clip.z || in.position.z > frame.clip.w {
        discard;
    }
    let fine = textureSample(own_texture, patch_sampler, in.local * piece.uv.x + piece.uv.yz).rgb;
    let coarse = textureSample(parent_texture, patch_sampler, in.local * piece.uv.w + piece.parent_uv.xy).rgb;
    // Figure 10: each side's weight falls from 1 at the side to 0 a quarter of the patch in;
    // the patch's own morph takes what the sides leave.
    let extent = piece.parent_uv.z;
    let t = clamp(in.local / extent, vec2<f32>(0.0), vec2<f32>(1.0));
    var w = clamp(vec4<f32>(1.0 - 4.0 * t.x, 1.0 - 4.0 * (1.0 - t.x), 1.0 - 4.0 * t.y, 1.0 - 4.0 * (1.0 - t.y)), vec4<f32>(0.0), vec4<f32>(1.0));
    let total = w.x + w.y + w.z + w.w;
    if total > 1.0 {
        w = w / total;
    }
    let blend = dot(piece.blend, w) + piece.spacing.z * (1.0 - min(total, 1.0));
    let albedo = mix(fine, coarse, clamp(blend, 0.0, 1.0));
    let lambert = max(dot(normalize(in.normal), frame.light_dir.xyz), 0.0);
    let ambient = frame.params.x;
    return vec4<f32>(albedo * (ambient + (1.0 - ambient) * lambert), 1.0);
}
