
// The sample arena as an integer texture, word k at texel (k % SAMPLE_TEXTURE_WIDTH,
// k / SAMPLE_TEXTURE_WIDTH): for backends whose vertex shaders read no storage buffers
// (WebGL2). Appended to terrain.wgsl: `TERRAIN_TEXTURE_SAMPLES`.
const SAMPLE_TEXTURE_WIDTH: u32 = 256u;
@group(1) @binding(0) var words: texture_2d<u32>;

fn word_at(k: u32) -> u32 {
    return textureLoad(words, vec2<u32>(k % SAMPLE_TEXTURE_WIDTH, k / SAMPLE_TEXTURE_WIDTH), 0).x;
}
