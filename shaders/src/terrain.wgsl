// Terrain tiles: one vertex shader for a tile's surface, skirts and planar shadow (indexed
// triangle strips over its samples), one fragment shader.
//
// Everything a tile needs is bound once a pass: the frame's tiles' parameters (one buffer of
// per-instance vertex attributes: a draw's first instance picks its tile) and the resident
// tiles' samples (16-bit height codes, two a word, in one storage array or, on WebGL2, one
// integer texture). Only the texture
// changes between draws. Per-instance attributes are fetched once per draw, where a storage
// read of the same data would be repeated for every vertex.
//
// Render space is camera-relative and right-handed: x east, y up, z south, in metres, with
// the camera at the origin. The Rust mirrors of these structs are in src/lib.rs.

struct Frame {
    // Camera-relative render space to clip space (reversed depth: near is 1, far is 0).
    view_proj: mat4x4<f32>,
    // Unit vector towards the light, render space.
    light_dir: vec4<f32>,
    // x: ambient share of the light, in [0, 1]; y: a pixel's height per metre of distance
    // along the view axis.
    params: vec4<f32>,
    // The camera relative to its anchor sample: (east m, height m, south m). Positions are
    // (sample index relative to the anchor) * spacing - this, so two tiles compute a
    // shared border sample from the same integers and place it bit for bit identically.
    camera: vec4<f32>,
    // The terrain's edge in render space (west x, north z, east x, south z): the real
    // samples end there, and what lies past it (the padding of the last tiles, anything a
    // method draws beyond) is discarded.
    clip: vec4<f32>,
};

// The tile being drawn: its parameters, per-instance attributes (`TileUniform` in Rust, one
// per drawn tile and frame). `codes` and `metres` are what turn `words` into heights.
struct Tile {
    // Sample (0, 0) of the tile as sample indices relative to the camera's anchor sample:
    // (east, 0, south). Whole numbers, exact in f32 up to 2^24.
    @location(0) origin: vec4<f32>,
    // x, y: metres between samples east and south; z: samples per side; w: skirt bottom
    // (the method's floor below the tile), metres above the datum.
    @location(1) spacing: vec4<f32>,
    // The paper's planar shadow: its corners (north-west, south-west, north-east,
    // south-east) in render space, already projected from the viewpoint onto the plane
    // below the tile (on the CPU: four points a tile, see the strip-mask method's
    // `shadow_corner`). The banded planar shadow (`shadow_band`): per side (north, east,
    // south, west), point0 the largest gap along a seam (metres) and point1 the mask the
    // neighbour draws (-1: a seam); point2.x the tile's own mask.
    @location(2) point0: vec4<f32>,
    @location(3) point1: vec4<f32>,
    @location(4) point2: vec4<f32>,
    @location(5) point3: vec4<f32>,
    // Where the tile lies in the texture bound with it: uv = xy + (column, row) / cells * zw.
    // (0, 0, 1, 1) for a tile's own texture; a part of a MapBlock's texture otherwise.
    @location(6) uv: vec4<f32>,
    // x: the tile's first word in `words`; y: its code base; z: its code shift. Sample i's
    // height code is base + (the 16 bits of sample i << shift).
    @location(7) codes: vec4<i32>,
    // x: metres per code (the quantum); y: metres at code 0 (the offset).
    @location(8) metres: vec4<f32>,
};

@group(0) @binding(0) var<uniform> frame: Frame;
// The resident tiles' height codes, 16 bits each, two a word (sample 2k in the low half), are
// read by `word_at(k)`, word k of the sample arena (group 1). It is declared by one of two
// files appended to this one (see the crate's `TERRAIN` and `TERRAIN_TEXTURE_SAMPLES`): a
// storage array, or where vertex shaders have no storage buffers (WebGL2) an integer texture.
// The texture a tile is drawn with: its own, or its MapBlock's, bound once for every tile of
// the block.
@group(2) @binding(0) var tile_texture: texture_2d<f32>;
@group(2) @binding(1) var tile_sampler: sampler;

// The tile being drawn, set at the start of the vertex shader.
var<private> tile: Tile;

struct Varyings {
    @builtin(position) clip: vec4<f32>,
    @location(0) uv: vec2<f32>,
    @location(1) normal: vec3<f32>,
    // Render-space position, for the clip at the terrain's edge.
    @location(2) position: vec3<f32>,
};

// What the unclipped fragment shader takes: no position to interpolate (a software
// rasteriser pays for every varying of every pixel).
struct Shaded {
    @builtin(position) clip: vec4<f32>,
    @location(0) uv: vec2<f32>,
    @location(1) normal: vec3<f32>,
};

// Render-space position of sample (column, row) at `height`.
fn position_of(column: u32, row: u32, height: f32) -> vec3<f32> {
    return vec3<f32>(
        (tile.origin.x + f32(column)) * tile.spacing.x - frame.camera.x,
        height - frame.camera.y,
        (tile.origin.z + f32(row)) * tile.spacing.y - frame.camera.z,
    );
}

// Clip position and texture coordinates of sample (column, row) at `height`.
fn place(column: u32, row: u32, height: f32) -> Varyings {
    let cells = tile.spacing.z - 1.0;
    let position = position_of(column, row, height);
    var out: Varyings;
    out.clip = frame.view_proj * vec4<f32>(position, 1.0);
    out.position = position;
    out.uv = tile.uv.xy + vec2<f32>(f32(column), f32(row)) / cells * tile.uv.zw;
    out.normal = vec3<f32>(0.0, 1.0, 0.0);
    return out;
}

// One vertex shader for everything a tile draws, told apart by the index:
// - below n*n: sample i (the strip masks);
// - n*n + i: the foot of sample i's skirt, at the skirt's bottom;
// - 2*n*n + k, k in 0..4: corner k of the paper's planar shadow;
// - 2*n*n + 4 + j, j in 0..8n: a vertex of the planar shadow's bands (`shadow_band`).
// One pipeline for all three keeps the render pass free of pipeline switches.
@vertex
fn vs_surface(@builtin(vertex_index) vertex: u32, drawn: Tile) -> Shaded {
    tile = drawn;
    let v = vertex_of(vertex);
    return Shaded(v.clip, v.uv, v.normal);
}

// The same, with the position for the clip at the terrain's edge (`fs_clipped`).
@vertex
fn vs_clipped(@builtin(vertex_index) vertex: u32, drawn: Tile) -> Varyings {
    tile = drawn;
    return vertex_of(vertex);
}

// Height of sample `i` (row-major), metres above the datum. Two tiles of a level share
// their border samples' codes, quantum and offset, so they place them identically.
fn height_at(i: u32) -> f32 {
    let word = word_at(u32(tile.codes.x) + i / 2u);
    let local = (word >> ((i & 1u) * 16u)) & 0xffffu;
    let code = tile.codes.y + (i32(local) << u32(tile.codes.z));
    return f32(code) * tile.metres.x + tile.metres.y;
}

// Unit normal at sample (column, row), render space: central differences of the tile's
// heights, one-sided on its edges (render space is x east, y up, z south, so the normal of
// height(east, south) is (-dh/deast, 1, -dh/dsouth), normalized).
fn normal_at(column: u32, row: u32, n: u32) -> vec3<f32> {
    let x0 = max(column, 1u) - 1u;
    let x1 = min(column + 1u, n - 1u);
    let y0 = max(row, 1u) - 1u;
    let y1 = min(row + 1u, n - 1u);
    let dx = (height_at(row * n + x1) - height_at(row * n + x0))
        / (f32(max(x1 - x0, 1u)) * tile.spacing.x);
    let dy = (height_at(y1 * n + column) - height_at(y0 * n + column))
        / (f32(max(y1 - y0, 1u)) * tile.spacing.y);
    return normalize(vec3<f32>(-dx, 1.0, -dy));
}

fn vertex_of(vertex: u32) -> Varyings {
    let n = u32(tile.spacing.z);
    let count = n * n;
    if vertex >= 2u * count + 4u {
        return shadow_band(vertex - 2u * count - 4u);
    }
    if vertex >= 2u * count {
        return shadow_corner(vertex - 2u * count);
    }
    var index = vertex;
    var skirt = false;
    if vertex >= count {
        index = vertex - count;
        skirt = true;
    }
    let column = index % n;
    let row = index / n;
    var height = tile.spacing.w;
    if !skirt {
        height = height_at(index);
    }
    var out = place(column, row, height);
    out.normal = normal_at(column, row, n);
    return out;
}

// The planar shadow (strip-mask paper, section 5.4): a quad under the tile, its corners
// projected from the viewpoint onto a horizontal plane below the tile, textured like the
// tile. Corners 0..3 are the north-west, south-west, north-east and south-east corners, a
// two-triangle strip; their positions come projected in the tile's uniforms.
fn shadow_corner(corner: u32) -> Varyings {
    let n = u32(tile.spacing.z);
    let column = (corner / 2u) * (n - 1u);
    let row = (corner % 2u) * (n - 1u);
    var out = place(column, row, 0.0);
    var points = array<vec4<f32>, 4>(tile.point0, tile.point1, tile.point2, tile.point3);
    out.clip = frame.view_proj * vec4<f32>(points[corner].xyz, 1.0);
    out.position = points[corner].xyz;
    out.normal = normal_at(column, row, n);
    return out;
}

// Height at position k (0..n) of a side whose samples are `side_index(k)`, on the polyline
// through the samples a mask keeping every `step`-th one (and the last) keeps: what a tile
// drawn at mask step - 1 draws there.
fn polyline_at(side: u32, k: u32, step: u32, n: u32) -> f32 {
    let k0 = (k / step) * step;
    let h0 = height_at(side_index(side, k0, n));
    if k0 == k {
        return h0;
    }
    let k1 = min(k0 + step, n - 1u);
    let h1 = height_at(side_index(side, k1, n));
    return mix(h0, h1, f32(k - k0) / f32(k1 - k0));
}

// Row-major index of sample k along side `side` (north, east, south, west; k west to east
// or north to south).
fn side_index(side: u32, k: u32, n: u32) -> u32 {
    let last = n - 1u;
    if side == 0u {
        return k;
    } else if side == 1u {
        return k * n + last;
    } else if side == 2u {
        return last * n + k;
    }
    return k * n;
}

// How far a band reaches past the seams it meets, in pixels (`shadow_band`); the crack
// probe reaches twice as far.
const SLIVER_PX: f32 = 0.015625;

// The planar shadow cut to bands along the sides where a crack can open (the strip-mask
// method's `band_strip`). Vertex j < 4n is position k = j % n of side s = j / n: the point
// of the tile's own polyline there (mask point2.x), pushed back in depth along the ray from
// the viewpoint towards the horizontal plane at the crack's bottom there; j >= 4n is that
// point's foot on the plane. The crack's bottom: the lower of the two polylines at k when
// the neighbour is a tile of this level drawn at mask point1[s] (>= 0); along a seam
// (point1[s] < 0), the polyline less point0[s], the largest gap between it and the other
// level's along the side. On screen each band covers what a skirt hanging from the
// polyline down to the crack's bottom would, which holds the crack; in depth it lies
// behind the side, so behind the surfaces in front. Textured and lit like the side's
// sample, as skirts are.
fn shadow_band(j: u32) -> Varyings {
    let n = u32(tile.spacing.z);
    let e = j % (4u * n);
    let side = e / n;
    let k = e % n;
    let i = side_index(side, k, n);
    let column = i % n;
    let row = i / n;
    let step = u32(tile.point2.x) + 1u;
    let own = polyline_at(side, k, step, n);
    var floor = own - tile.point0[side];
    let across = tile.point1[side];
    if across >= 0.0 {
        let theirs = u32(across) + 1u;
        floor = min(own, polyline_at(side, k, theirs, n));
    }
    // The evaluation's crack probe (point2.y = 1): a skirt from the polyline straight down
    // to the skirts' bottom, not projected.
    let probe = tile.point2.y > 0.5;
    if probe {
        floor = tile.spacing.w;
    }
    // Between the bends of either polyline the band meets the surfaces at T-junctions, where
    // the rasteriser may leave a pixel on neither side: the band's top is lifted and its
    // foot lowered by a sliver of a pixel (`SLIVER_PX` of a pixel's footprint at the
    // point), which closes them; the surfaces in front still hide the overlap. The probe's
    // top is lifted twice as far, so that every pixel the band covers lies in the probe.
    var p = position_of(column, row, own);
    let top = frame.view_proj * vec4<f32>(p, 1.0);
    let sliver = SLIVER_PX * frame.params.y * top.w;
    var lift = 0.0;
    if probe {
        lift = 2.0 * sliver;
    } else if across >= 0.0 {
        lift = sliver;
        floor -= sliver;
    }
    var out = place(column, row, floor);
    out.normal = normal_at(column, row, n);
    if j < 4u * n {
        p.y += lift;
        let plane = floor - frame.camera.y;
        // On screen, the side's point itself, lifted by the sliver (the surface's edge to
        // the bit where nothing is lifted, along a seam between levels); in depth, pushed
        // back along the ray from the camera onto the plane, but no farther past the point
        // than a pixel's footprint there: a point farther behind stands for terrain away
        // from the crack (near grazing angles the plane lies far behind), and its error
        // shows through the crack.
        out.clip = top + frame.view_proj[1] * lift;
        if !probe {
            if plane < 0.0 {
                let reach = 1.0 + frame.params.y;
                let back = frame.view_proj * vec4<f32>(p * (-plane / max(-p.y, -plane / reach)), 1.0);
                out.clip.z = back.z / back.w * out.clip.w;
            } else {
                // The camera below the plane: nothing to project from, an empty band.
                out.clip = frame.view_proj * vec4<f32>(p.x, plane, p.z, 1.0);
            }
        }
        // Clipped at the terrain's edge by the side's own position, not the projected one:
        // a band hangs from a side inside the terrain wherever its plane point lies.
        out.position = p;
    }
    return out;
}

// Whether render-space `p` lies past the terrain's edge.
fn past_the_edge(p: vec3<f32>) -> bool {
    return p.x < frame.clip.x || p.z < frame.clip.y || p.x > frame.clip.z || p.z > frame.clip.w;
}

// Tiles whose surface and fillers may reach past the terrain's edge (at the border, or
// padded) are drawn with this one; the others with `fs_main`, which keeps the rasteriser's
// early depth test (a `discard` anywhere in a shader turns it off).
@fragment
fn fs_clipped(in: Varyings) -> @location(0) vec4<f32> {
    if past_the_edge(in.position) {
        discard;
    }
    return shade(in.uv, in.normal);
}

@fragment
fn fs_main(in: Shaded) -> @location(0) vec4<f32> {
    return shade(in.uv, in.normal);
}

fn shade(uv: vec2<f32>, normal: vec3<f32>) -> vec4<f32> {
    let albedo = textureSample(tile_texture, tile_sampler, uv).rgb;
    let lambert = max(dot(normalize(normal), frame.light_dir.xyz), 0.0);
    let ambient = frame.params.x;
    return vec4<f32>(albedo * (ambient + (1.0 - ambient) * lambert), 1.0);
}
