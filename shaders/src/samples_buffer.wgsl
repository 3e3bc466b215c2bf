
// The sample arena as a storage array (appended to terrain.wgsl: `TERRAIN`).
@group(1) @binding(0) var<storage, read> words: array<u32>;

fn word_at(k: u32) -> u32 {
    return words[k];
}
