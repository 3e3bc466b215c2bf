// Projected grids: persistent grid mapping (Livny et al.) and the error-bounded projective
// grid (Löffler et al.). A regular grid of vertices in the screen of an auxiliary camera,
// kept on the GPU, is cast each frame onto a plane below the terrain and displaced by the
// heights found there, in an atlas of the resident tiles' height pyramids. The error-bounded
// grid also writes an error buffer, and a second pass casts rays through the heights in
// the pixels it marks.
//
// Render space is camera-relative: x east, y up, z south, metres, the camera at the origin.
// Ground places are level-0 sample coordinates: a whole part (absolute, i32) and a fraction,
// so lookups stay exact however large the terrain. The Rust mirrors are in src/lib.rs.

struct Frame {
    view_proj: mat4x4<f32>,
    light_dir: vec4<f32>,
    params: vec4<f32>,
    // The camera relative to its anchor sample: (east m, height m, south m).
    camera: vec4<f32>,
    clip: vec4<f32>,
};

struct Grid {
    // The auxiliary camera's unit axes in render space; forward.w: the render-space height
    // of the plane the grid is cast onto (below the camera); right.w and up.w: the tangents
    // of its half fields of view.
    forward: vec4<f32>,
    right: vec4<f32>,
    up: vec4<f32>,
    // x, y: grid vertices per row and per column; z: farthest distance a ray is followed,
    // metres; w: flags (FLAG_*).
    size: vec4<f32>,
    // x, y: metres between level-0 samples east and south; z: the screen-space error
    // threshold gamma, pixels; w: the main camera's focal length, pixels.
    spacing: vec4<f32>,
    // x, y: the camera's anchor sample (level 0); z: pyramid levels; w: cells per tile side
    // (2^n).
    anchor: vec4<i32>,
    // x, y: the terrain's lowest and highest heights, metres; z: the main camera's tangents
    // of its half fields of view, x; w: the same, y.
    heights: vec4<f32>,
    // x, y: the colour atlas's size in texels; z: texels per colour slot side; w: floats per
    // height slot.
    colour: vec4<f32>,
    // x, y: the target's size in pixels; z, w: the raster's size in level-0 samples.
    screen: vec4<f32>,
    // The background colour (rgb), for rays that hit nothing.
    sky: vec4<f32>,
    // The main camera's clip space back to render space.
    inverse_view_proj: mat4x4<f32>,
    // Per pyramid level: x the first entry of its slot table, y its columns, z its rows.
    levels: array<vec4<u32>, 24>,
    // Per mip m of a slot: x the first float of its averaged heights, y the first float of
    // its min/max blocks (m >= 1), z samples per side, w blocks per side.
    mips: array<vec4<u32>, 16>,
    // The warped grid (Löffler et al.): where grid line k of WARP_LINES sits, in [0, 1],
    // across (u) and down (v) the auxiliary screen.
    warp_u: array<vec4<f32>, 9>,
    warp_v: array<vec4<f32>, 9>,
};

struct SlotInfo {
    // x: the tile's distance from the full-resolution surface, metres; y, z: the lowest and
    // highest points of the full-resolution surface under it.
    bounds: vec4<f32>,
    // x, y: the slot's place in the colour atlas (column, row); z, w: its finest and
    // coarsest colour mips holding the tile's texture.
    colour: vec4<u32>,
};

struct Counters {
    // Pixels whose ray was walked (it enters the terrain's box), and of the pixels the
    // error buffer marks those the grid covered with an error past the threshold.
    rays: atomic<u32>,
    errors: atomic<u32>,
    // Pixels whose ray hit the terrain.
    hits: atomic<u32>,
    // Pixels the error buffer marks: past the threshold, or not covered by the grid.
    marked: atomic<u32>,
};

const FLAG_WARP: u32 = 1u;
const FLAG_ERROR_BOUNDED: u32 = 2u;
const FLAG_RAY_CASTING: u32 = 4u;
const WARP_LINES: u32 = 33u;
// The error buffer's clear value: no grid triangle covers the pixel.
const UNCOVERED: f32 = 2.0;

@group(0) @binding(0) var<uniform> frame: Frame;
// A read-only storage buffer, not a uniform one: with the grid's parameters in a uniform
// buffer, rewritten every frame, lavapipe made the process grow by 1.8 to 4.3 MB a frame
// (flight.csv's rss_bytes; heap and GPU allocations flat), and does not from a storage
// buffer. The values read are the same; see `footprint_of` for the one care they need.
@group(1) @binding(0) var<storage, read> grid: Grid;
@group(1) @binding(1) var<storage, read> atlas: array<f32>;
@group(1) @binding(2) var<storage, read> table: array<u32>;
@group(1) @binding(3) var<storage, read> slots: array<SlotInfo>;
@group(1) @binding(4) var colour_atlas: texture_2d<f32>;
@group(1) @binding(5) var colour_sampler: sampler;
@group(2) @binding(0) var error_buffer: texture_2d<f32>;
@group(2) @binding(1) var<storage, read_write> counters: Counters;

// A place on the ground in level-0 samples.
struct Place {
    whole: vec2<i32>,
    part: vec2<f32>,
};

fn place_of(p: vec3<f32>) -> Place {
    let s = vec2<f32>(frame.camera.x + p.x, frame.camera.z + p.z) / grid.spacing.xy;
    let f = floor(s);
    return Place(grid.anchor.xy + vec2<i32>(f), s - f);
}

fn moved(q: Place, by: vec2<f32>) -> Place {
    let s = q.part + by;
    let f = floor(s);
    return Place(q.whole + vec2<i32>(f), s - f);
}

// A tile of the atlas under a place: its slot (-1: none) and the place in the tile's own
// samples.
struct Found {
    slot: i32,
    local: vec2<f32>,
};

fn find(level: u32, q: Place) -> Found {
    var none = Found(-1, vec2<f32>(0.0));
    if level >= u32(grid.anchor.z) {
        return none;
    }
    let lv = grid.levels[level];
    let cells = grid.anchor.w;
    let whole = q.whole >> vec2<u32>(level);
    if whole.x < 0 || whole.y < 0 {
        return none;
    }
    let tile = whole / cells;
    if tile.x >= i32(lv.y) || tile.y >= i32(lv.z) {
        return none;
    }
    let entry = table[lv.x + u32(tile.y) * lv.y + u32(tile.x)];
    if entry == 0u {
        return none;
    }
    let mask = (1 << level) - 1;
    let fraction = (vec2<f32>(q.whole & vec2<i32>(mask)) + q.part) / f32(1u << level);
    return Found(i32(entry) - 1, vec2<f32>(whole - tile * cells) + fraction);
}

// Height at (u, v) of a cell split along the diagonal from (0, 1) to (1, 0), as every
// strip mask draws it (`terrain_shared::mask::cell_height`).
fn cell_height(h00: f32, h10: f32, h01: f32, h11: f32, f: vec2<f32>) -> f32 {
    if f.x + f.y <= 1.0 {
        return h00 + f.x * (h10 - h00) + f.y * (h01 - h00);
    }
    return h11 + (1.0 - f.x) * (h01 - h11) + (1.0 - f.y) * (h10 - h11);
}

// The averaged heights of mip m of a slot at `local` (the tile's own samples).
fn averaged(slot: i32, m: u32, local: vec2<f32>) -> f32 {
    let mip = grid.mips[m];
    let base = u32(slot) * u32(grid.colour.w) + mip.x;
    let side = mip.z;
    let c = local / f32(1u << m);
    let i = min(vec2<u32>(max(floor(c), vec2<f32>(0.0))), vec2<u32>(side - 2u));
    let f = clamp(c - vec2<f32>(i), vec2<f32>(0.0), vec2<f32>(1.0));
    let at = base + i.y * side + i.x;
    return cell_height(atlas[at], atlas[at + 1u], atlas[at + side], atlas[at + side + 1u], f);
}

// The surface averaged to level `w` at `q` (x), and the distance of the tile it came from
// from full resolution (y; negative: no tile holds the place). The tile is the coarsest
// resident one no coarser than `w` (its mip w - level), else the finest coarser one.
fn surface(w: u32, q: Place) -> vec2<f32> {
    let levels = u32(grid.anchor.z);
    let n = countTrailingZeros(u32(grid.anchor.w));
    let top = min(w, levels - 1u);
    for (var l = i32(top); l >= 0; l -= 1) {
        let hit = find(u32(l), q);
        if hit.slot >= 0 {
            let m = min(w - u32(l), n);
            return vec2<f32>(averaged(hit.slot, m, hit.local), slots[hit.slot].bounds.x);
        }
    }
    for (var l = top + 1u; l < levels; l += 1u) {
        let hit = find(l, q);
        if hit.slot >= 0 {
            return vec2<f32>(averaged(hit.slot, 0u, hit.local), slots[hit.slot].bounds.x);
        }
    }
    return vec2<f32>(grid.heights.x, -1.0);
}

fn warp(table_: ptr<function, array<vec4<f32>, 9>>, s: f32) -> f32 {
    let x = clamp(s, 0.0, 1.0) * f32(WARP_LINES - 1u);
    let k = min(u32(floor(x)), WARP_LINES - 2u);
    let a = (*table_)[k / 4u][k % 4u];
    let b = (*table_)[(k + 1u) / 4u][(k + 1u) % 4u];
    return mix(a, b, x - f32(k));
}

// Grid vertex (i, j) on the auxiliary screen, in [0, 1]^2 from the top left: uniform, or
// through the warp tables.
fn grid_uv(i: i32, j: i32) -> vec2<f32> {
    let cols = grid.size.x;
    let rows = grid.size.y;
    let uv = vec2<f32>(f32(i) / (cols - 1.0), f32(j) / (rows - 1.0));
    if (u32(grid.size.w) & FLAG_WARP) == 0u {
        return uv;
    }
    var wu = grid.warp_u;
    var wv = grid.warp_v;
    return vec2<f32>(warp(&wu, uv.x), warp(&wv, uv.y));
}

// Where the ray of auxiliary screen point `uv` meets the plane below the terrain (render
// space), or the point at the farthest distance along it.
fn ground_of(uv: vec2<f32>) -> vec3<f32> {
    let x = uv.x * 2.0 - 1.0;
    let y = 1.0 - uv.y * 2.0;
    let d = normalize(grid.forward.xyz + x * grid.right.w * grid.right.xyz + y * grid.up.w * grid.up.xyz);
    let plane = grid.forward.w;
    var t = grid.size.z;
    if d.y < -1e-7 {
        t = min(plane / d.y, t);
    }
    return vec3<f32>(d.x * t, plane, d.z * t);
}

struct GridVertex {
    @builtin(position) clip: vec4<f32>,
    @location(0) position: vec3<f32>,
    @location(1) normal: vec3<f32>,
    // 1 where the heights are known.
    @location(2) flags: f32,
};

@vertex
fn vs_grid(@builtin(vertex_index) index: u32) -> GridVertex {
    let cols = i32(grid.size.x);
    let rows = i32(grid.size.y);
    let i = i32(index) % cols;
    let j = i32(index) / cols;
    let p = ground_of(grid_uv(i, j));
    // The farthest adjacent neighbour on the ground (Livny et al., figure 9), exactly rather
    // than by equation 3's approximation: four more rays.
    var r = 0.0;
    for (var k = 0; k < 4; k += 1) {
        let di = select(select(-1, 1, k == 1), 0, k >= 2);
        let dj = select(0, select(-1, 1, k == 3), k >= 2);
        let ni = clamp(i + di, 0, cols - 1);
        let nj = clamp(j + dj, 0, rows - 1);
        let q = ground_of(grid_uv(ni, nj));
        r = max(r, length((q - p).xz));
    }
    let s0 = min(grid.spacing.x, grid.spacing.y);
    // The pyramid level whose samples are r apart (Löffler et al., equation 1), and the
    // parent's weight rising linearly across the level (Livny et al., equation 4). The
    // error-bounded grid takes the level a step finer, its samples r / 2 apart: its vertices
    // then follow the surface rather than its average over their cells, and fewer pixels
    // pass the threshold (Puget Sound, 256x144 at 640x360: the most in a camera's view went
    // from 22% to 11%).
    var bias = 0.0;
    if (u32(grid.size.w) & FLAG_ERROR_BOUNDED) != 0u {
        bias = 1.0;
    }
    let lod = min(max(log2(max(r, 1e-6) / s0) - bias, 0.0), 30.0);
    let w = u32(floor(lod));
    let parent_weight = lod - floor(lod);
    let q = place_of(p);
    let fine = surface(w, q);
    let parent = surface(w + 1u, q);
    let h = mix(fine.x, parent.x, parent_weight);
    // The normal from central differences at the level's spacing.
    let d = f32(1u << w);
    let hx0 = surface(w, moved(q, vec2<f32>(-d, 0.0))).x;
    let hx1 = surface(w, moved(q, vec2<f32>(d, 0.0))).x;
    let hy0 = surface(w, moved(q, vec2<f32>(0.0, -d))).x;
    let hy1 = surface(w, moved(q, vec2<f32>(0.0, d))).x;
    let normal = normalize(vec3<f32>(
        -(hx1 - hx0) / (2.0 * d * grid.spacing.x),
        1.0,
        -(hy1 - hy0) / (2.0 * d * grid.spacing.y),
    ));
    var out: GridVertex;
    out.position = vec3<f32>(p.x, h - frame.camera.y, p.z);
    out.clip = frame.view_proj * vec4<f32>(out.position, 1.0);
    out.normal = normal;
    out.flags = select(0.0, 1.0, fine.y >= 0.0);
    return out;
}

fn past_the_edge(p: vec3<f32>) -> bool {
    return p.x < frame.clip.x || p.z < frame.clip.y || p.x > frame.clip.z || p.z > frame.clip.w;
}

// The colour at `q` for a footprint of `footprint` level-0 samples: from the finest tile in
// the atlas no finer than the footprint needs, at the mip of its texture that matches.
fn albedo_at(q: Place, footprint: f32) -> vec3<f32> {
    let levels = u32(grid.anchor.z);
    let cells = f32(grid.anchor.w);
    let side = grid.colour.z;
    let wanted = u32(clamp(floor(log2(max(footprint * side / cells, 1e-6))), 0.0, f32(levels - 1u)));
    var hit = Found(-1, vec2<f32>(0.0));
    var level = 0u;
    for (var l = i32(wanted); l >= 0; l -= 1) {
        hit = find(u32(l), q);
        if hit.slot >= 0 {
            level = u32(l);
            break;
        }
    }
    if hit.slot < 0 {
        for (var l = wanted + 1u; l < levels; l += 1u) {
            hit = find(l, q);
            if hit.slot >= 0 {
                level = l;
                break;
            }
        }
    }
    if hit.slot < 0 {
        return vec3<f32>(0.5);
    }
    let info = slots[hit.slot].colour;
    let texels = footprint / f32(1u << level) * side / cells;
    let lod = clamp(log2(max(texels, 1e-6)), f32(info.z), f32(info.w));
    let size = side / f32(1u << u32(ceil(lod)));
    let half = 0.5 / size;
    let uv = clamp(hit.local / cells, vec2<f32>(half), vec2<f32>(1.0 - half));
    let at = (vec2<f32>(info.xy) + uv) * side / grid.colour.xy;
    return textureSampleLevel(colour_atlas, colour_sampler, at, lod).rgb;
}

fn shade(albedo: vec3<f32>, normal: vec3<f32>) -> vec4<f32> {
    let lambert = max(dot(normalize(normal), frame.light_dir.xyz), 0.0);
    let ambient = frame.params.x;
    return vec4<f32>(albedo * (ambient + (1.0 - ambient) * lambert), 1.0);
}

// The footprint of a pixel at render-space `p`, in level-0 samples. The derivatives are
// of `p` alone, scaled after: llvmpipe masks storage loads in the helper pixels of a quad
// (they read 0), so a derivative of anything read from `grid` is noise there.
fn footprint_of(p: vec3<f32>) -> vec2<f32> {
    let dx = dpdx(vec2<f32>(p.x, p.z)) / grid.spacing.xy;
    let dy = dpdy(vec2<f32>(p.x, p.z)) / grid.spacing.xy;
    return vec2<f32>(length(dx), length(dy));
}

@fragment
fn fs_grid(in: GridVertex) -> @location(0) vec4<f32> {
    let f = footprint_of(in.position);
    if past_the_edge(in.position) || in.flags < 0.999 {
        discard;
    }
    return shade(albedo_at(place_of(in.position), max(f.x, f.y)), in.normal);
}

// The error of the grid at the point a pixel draws, normalised (Löffler et al., equation 4:
// 0 within the threshold, 1 - gamma / rho past it). The grid's height there is set against
// the surface's own at the same place: the triangles of the finest resident tile's samples
// (as the reference draws them), widened by that tile's distance from full resolution,
// which is 0 at level 0. That vertical distance is turned into pixels as a vertical segment
// at the point: the main camera's pixels per radian where it lands (the focal length times
// sec^2 of the angle off the axis, an upper bound across the screen) over its distance.
// Per pixel rather than per vertex: a bound over a vertex's whole region (the range of
// heights within reach, as Löffler et al. take it) counts a smooth slope's rise as error,
// and marked most pixels of every view past 1 px.
fn pixel_error(p: vec3<f32>) -> f32 {
    let truth = surface(0u, place_of(p));
    if truth.y < 0.0 {
        return UNCOVERED;
    }
    let delta = abs(p.y + frame.camera.y - truth.x) + truth.y;
    let clip = frame.view_proj * vec4<f32>(p, 1.0);
    let ndc = clamp(clip.xy / max(clip.w, 1e-6), vec2<f32>(-1.0), vec2<f32>(1.0));
    let off_axis = ndc * grid.heights.zw;
    let lambda = grid.spacing.w * (1.0 + dot(off_axis, off_axis));
    let rho = lambda * delta / max(length(p), 1e-3);
    let gamma = grid.spacing.z;
    if rho > gamma {
        return 1.0 - gamma / rho;
    }
    return 0.0;
}

struct GridOutput {
    @location(0) colour: vec4<f32>,
    // The error buffer (Löffler et al., figure 7): 0 within the threshold.
    @location(1) error: vec4<f32>,
};

@fragment
fn fs_grid_error(in: GridVertex) -> GridOutput {
    let f = footprint_of(in.position);
    if past_the_edge(in.position) || in.flags < 0.999 {
        discard;
    }
    var out: GridOutput;
    out.colour = shade(albedo_at(place_of(in.position), max(f.x, f.y)), in.normal);
    out.error = vec4<f32>(pixel_error(in.position), 0.0, 0.0, 0.0);
    return out;
}

// --- Ray casting (Löffler et al., section 4: "Rendering") ---

@vertex
fn vs_fullscreen(@builtin(vertex_index) index: u32) -> @builtin(position) vec4<f32> {
    let x = f32((index << 1u) & 2u) * 2.0 - 1.0;
    let y = f32(index & 2u) * 2.0 - 1.0;
    return vec4<f32>(x, y, 0.0, 1.0);
}

// A ray in the samples of one tile: local = a + b t, height = h0 + dh t.
struct Ray {
    a: vec2<f32>,
    b: vec2<f32>,
    h0: f32,
    dh: f32,
};

struct Hit {
    t: f32,
    normal: vec3<f32>,
};

fn ray_height(ray: Ray, t: f32) -> f32 {
    return ray.h0 + ray.dh * t;
}

// The t at which the ray leaves the square [lo, lo + size]^2 (local coordinates).
fn exit_of(ray: Ray, lo: vec2<f32>, size: f32, t: f32) -> f32 {
    var out = 3.4e38;
    for (var k = 0; k < 2; k += 1) {
        let b = ray.b[k];
        if abs(b) > 1e-12 {
            let edge = select(lo[k], lo[k] + size, b > 0.0);
            out = min(out, (edge - ray.a[k]) / b);
        }
    }
    return max(out, t);
}

fn sample_of(slot: i32, side: u32, c: vec2<u32>) -> f32 {
    return atlas[u32(slot) * u32(grid.colour.w) + c.y * side + c.x];
}

// Where the ray meets the two triangles of cell `c` of the slot's samples (Möller and
// Trumbore's test in the tile's own coordinates: t does not change under their scaling).
fn cell_hit(ray: Ray, slot: i32, side: u32, c: vec2<u32>, t_min: f32, t_max: f32, metres: vec2<f32>) -> Hit {
    let h00 = sample_of(slot, side, c);
    let h10 = sample_of(slot, side, c + vec2<u32>(1u, 0u));
    let h01 = sample_of(slot, side, c + vec2<u32>(0u, 1u));
    let h11 = sample_of(slot, side, c + vec2<u32>(1u, 1u));
    let o = vec3<f32>(vec2<f32>(c), 0.0);
    let p00 = o + vec3<f32>(0.0, 0.0, h00);
    let p10 = o + vec3<f32>(1.0, 0.0, h10);
    let p01 = o + vec3<f32>(0.0, 1.0, h01);
    let p11 = o + vec3<f32>(1.0, 1.0, h11);
    let origin = vec3<f32>(ray.a, ray.h0);
    let dir = vec3<f32>(ray.b, ray.dh);
    var best = Hit(-1.0, vec3<f32>(0.0, 1.0, 0.0));
    for (var k = 0; k < 2; k += 1) {
        var v0 = p00;
        var v1 = p10;
        var v2 = p01;
        if k == 1 {
            v0 = p11;
            v1 = p01;
            v2 = p10;
        }
        let e1 = v1 - v0;
        let e2 = v2 - v0;
        let pv = cross(dir, e2);
        let det = dot(e1, pv);
        if abs(det) < 1e-20 {
            continue;
        }
        let inv = 1.0 / det;
        let tv = origin - v0;
        let u = dot(tv, pv) * inv;
        let qv = cross(tv, e1);
        let v = dot(dir, qv) * inv;
        let t = dot(e2, qv) * inv;
        let slack = 1e-4;
        if u >= -slack && v >= -slack && u + v <= 1.0 + slack && t >= t_min && t <= t_max && (best.t < 0.0 || t < best.t) {
            // The triangle's slope in metres gives its normal (render space).
            let sign = select(1.0, -1.0, k == 1);
            let du = sign * e1.z / metres.x;
            let dv = sign * e2.z / metres.y;
            best = Hit(t, normalize(vec3<f32>(-du, 1.0, -dv)));
        }
    }
    return best;
}

// Casts the ray through one tile between t0 and t1: blocks of BLOCK_MIP whose bounds the
// ray passes are searched cell by cell. Both walks step from cell to cell along the ray
// (Amanatides and Woo), so no cell is skipped however the ray meets their corners.
const BLOCK_MIP: u32 = 3u;

// A walk over the cells of side `size` of a grid, along the ray from t.
struct Walk {
    cell: vec2<i32>,
    step: vec2<i32>,
    next: vec2<f32>,
    delta: vec2<f32>,
};

fn walk_from(ray: Ray, size: f32, t: f32, nudge: f32) -> Walk {
    let at = ray.a + ray.b * (t + nudge);
    let cell = vec2<i32>(floor(at / size));
    var w: Walk;
    w.cell = cell;
    for (var k = 0; k < 2; k += 1) {
        let b = ray.b[k];
        if abs(b) < 1e-12 {
            w.step[k] = 0;
            w.next[k] = 3.4e38;
            w.delta[k] = 3.4e38;
        } else {
            w.step[k] = select(-1, 1, b > 0.0);
            let edge = (f32(cell[k]) + select(0.0, 1.0, b > 0.0)) * size;
            w.next[k] = max((edge - ray.a[k]) / b, t);
            w.delta[k] = size / abs(b);
        }
    }
    return w;
}

// The t at which the walk leaves its cell.
fn walk_exit(w: Walk) -> f32 {
    return min(w.next.x, w.next.y);
}

fn walk_step(w: ptr<function, Walk>) {
    if (*w).next.x < (*w).next.y {
        (*w).cell.x += (*w).step.x;
        (*w).next.x += (*w).delta.x;
    } else {
        (*w).cell.y += (*w).step.y;
        (*w).next.y += (*w).delta.y;
    }
}

fn tile_hit(ray: Ray, slot: i32, level: u32, t0: f32, t1: f32) -> Hit {
    let n = countTrailingZeros(u32(grid.anchor.w));
    let side = grid.mips[0].z;
    let cells = i32(grid.anchor.w);
    let m = min(BLOCK_MIP, n);
    let mip = grid.mips[m];
    let per_side = i32(mip.w);
    let block = f32(1u << m);
    let metres = grid.spacing.xy * f32(1u << level);
    // Steps past a boundary, to find the cell beyond it: a thousandth of a cell along the
    // ray, whatever the ray's length.
    let nudge = 1e-3 / max(max(abs(ray.b.x), abs(ray.b.y)), 1e-12);
    var blocks = walk_from(ray, block, t0, nudge);
    var t = t0;
    for (var guard = 0u; guard < 2u * u32(per_side) + 4u; guard += 1u) {
        if t >= t1 {
            break;
        }
        let t_exit = min(walk_exit(blocks), t1);
        let bi = blocks.cell;
        if all(bi >= vec2<i32>(0)) && all(bi < vec2<i32>(per_side)) {
            let k = u32(slot) * u32(grid.colour.w) + mip.y + 2u * (u32(bi.y * per_side + bi.x));
            let za = ray_height(ray, t);
            let zb = ray_height(ray, t_exit);
            if min(za, zb) <= atlas[k + 1u] && max(za, zb) >= atlas[k] {
                // Every cell of the block the ray crosses, nearest first.
                var walk = walk_from(ray, 1.0, t, nudge);
                var tc = t;
                for (var inner = 0u; inner < 2u * (1u << m) + 4u; inner += 1u) {
                    if tc >= t_exit {
                        break;
                    }
                    let tc_exit = min(walk_exit(walk), t_exit);
                    let c = walk.cell;
                    if all(c >= vec2<i32>(0)) && all(c < vec2<i32>(cells)) {
                        let hit = cell_hit(ray, slot, side, vec2<u32>(c), tc - 1e-3, tc_exit + 1e-3, metres);
                        if hit.t >= 0.0 {
                            return hit;
                        }
                    }
                    tc = tc_exit;
                    walk_step(&walk);
                }
            }
        }
        t = t_exit;
        walk_step(&blocks);
    }
    return Hit(-1.0, vec3<f32>(0.0, 1.0, 0.0));
}

// Casts the render-space ray from the camera along unit `d` through the finest tiles the
// atlas holds, tile by tile, skipping a tile whose bounds the ray passes above or below.
fn cast_ray(d: vec3<f32>) -> Hit {
    let levels = u32(grid.anchor.z);
    let cells = f32(grid.anchor.w);
    let eye_h = frame.camera.y;
    // The ray in level-0 samples relative to the anchor, and metres of height.
    let o = vec2<f32>(frame.camera.x, frame.camera.z) / grid.spacing.xy;
    let b = vec2<f32>(d.x, d.z) / grid.spacing.xy;
    // Clip t to the terrain's box: the raster's samples, the lowest and highest heights.
    var t0 = 0.0;
    var t1 = grid.size.z;
    let lo = -vec2<f32>(grid.anchor.xy);
    let hi = lo + grid.screen.zw - 1.0;
    for (var k = 0; k < 2; k += 1) {
        if abs(b[k]) < 1e-12 {
            if o[k] < lo[k] || o[k] > hi[k] {
                return Hit(-1.0, vec3<f32>(0.0));
            }
        } else {
            let ta = (lo[k] - o[k]) / b[k];
            let tb = (hi[k] - o[k]) / b[k];
            t0 = max(t0, min(ta, tb));
            t1 = min(t1, max(ta, tb));
        }
    }
    // A metre of slack above and below: a flat surface at the lowest height (the sea) lies
    // on the box's floor, where the walk would stop before testing it.
    if abs(d.y) > 1e-12 {
        let ta = (grid.heights.x - 1.0 - eye_h) / d.y;
        let tb = (grid.heights.y + 1.0 - eye_h) / d.y;
        t0 = max(t0, min(ta, tb));
        t1 = min(t1, max(ta, tb));
    } else if eye_h < grid.heights.x || eye_h > grid.heights.y {
        return Hit(-1.0, vec3<f32>(0.0));
    }
    if t0 >= t1 {
        return Hit(-1.0, vec3<f32>(0.0));
    }
    atomicAdd(&counters.rays, 1u);
    var t = t0;
    var guard = 0u;
    loop {
        if t >= t1 || guard > 512u {
            break;
        }
        guard += 1u;
        // A thousandth of a level-0 sample past the boundary: far enough to be in the next
        // tile, too little to step over a cell.
        let s = o + b * (t + 1e-3 / max(max(abs(b.x), abs(b.y)), 1e-12));
        let f = floor(s);
        let q = Place(grid.anchor.xy + vec2<i32>(f), s - f);
        // The finest tile holding the place.
        var hit = Found(-1, vec2<f32>(0.0));
        var level = 0u;
        for (var l = 0u; l < levels; l += 1u) {
            hit = find(l, q);
            if hit.slot >= 0 {
                level = l;
                break;
            }
        }
        let scale = f32(1u << select(levels - 1u, level, hit.slot >= 0));
        // The tile's square in level-0 samples relative to the anchor.
        let tile_size = cells * scale;
        let origin = floor((s + vec2<f32>(grid.anchor.xy)) / tile_size) * tile_size - vec2<f32>(grid.anchor.xy);
        let ray = Ray((o - origin) / scale, b / scale, eye_h, d.y);
        let t_exit = min(exit_of(ray, vec2<f32>(0.0), cells, t), t1);
        if hit.slot >= 0 {
            let bounds = slots[hit.slot].bounds;
            let za = ray_height(ray, t);
            let zb = ray_height(ray, t_exit);
            if min(za, zb) <= bounds.z && max(za, zb) >= bounds.y {
                let found = tile_hit(ray, hit.slot, level, t, t_exit);
                if found.t >= 0.0 {
                    return found;
                }
            }
        }
        if t_exit <= t {
            break;
        }
        t = t_exit;
    }
    return Hit(-1.0, vec3<f32>(0.0));
}

struct RayOutput {
    @location(0) colour: vec4<f32>,
    @builtin(frag_depth) depth: f32,
};

// Pixels the error buffer marks (past the threshold, or not covered by the grid) are ray
// cast: exact colour and depth replace the grid's.
@fragment
fn fs_ray(@builtin(position) pixel: vec4<f32>) -> RayOutput {
    let e = textureLoad(error_buffer, vec2<i32>(pixel.xy), 0).x;
    if e <= 0.0 {
        discard;
    }
    if e <= 1.0 {
        atomicAdd(&counters.errors, 1u);
    }
    // Without ray casting the pass only counts the pixels past the threshold.
    if (u32(grid.size.w) & FLAG_RAY_CASTING) == 0u {
        discard;
    }
    atomicAdd(&counters.marked, 1u);
    let ndc = vec2<f32>(pixel.x / grid.screen.x * 2.0 - 1.0, 1.0 - pixel.y / grid.screen.y * 2.0);
    let far = grid.inverse_view_proj * vec4<f32>(ndc, 1.0, 1.0);
    let d = normalize(far.xyz / far.w);
    let hit = cast_ray(d);
    var out: RayOutput;
    if hit.t < 0.0 {
        out.colour = vec4<f32>(grid.sky.rgb, 1.0);
        out.depth = 0.0;
        return out;
    }
    atomicAdd(&counters.hits, 1u);
    let p = d * hit.t;
    let clip = frame.view_proj * vec4<f32>(p, 1.0);
    out.depth = clip.z / clip.w;
    // A pixel's footprint at distance t: t times its angle, in level-0 samples.
    let pixel_angle = 2.0 * grid.heights.w / grid.screen.y;
    let footprint = hit.t * pixel_angle / min(grid.spacing.x, grid.spacing.y);
    out.colour = shade(albedo_at(place_of(p), footprint), hit.normal);
    return out;
}
