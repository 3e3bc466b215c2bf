//! The memory invariant is stated once, in `terrain_client::memory::MEMORY_INVARIANT`, and
//! word for word in every place a reader looks for it: README.md, ARCHITECTURE.md,
//! docs/flight.md, docs/reliability.md and the scene's module documentation. Line breaks,
//! comment markers and Markdown quoting do not count; any other difference fails here.

use std::path::Path;
use terrain_client::memory::MEMORY_INVARIANT;

/// `text` with comment markers (`//!`, `///`) and quote markers dropped and every run of
/// whitespace made one space.
fn normalized(text: &str) -> String {
    text.lines()
        .map(|line| {
            let line = line.trim_start();
            line.strip_prefix("//!")
                .or_else(|| line.strip_prefix("///"))
                .or_else(|| line.strip_prefix('>'))
                .unwrap_or(line)
        })
        .collect::<Vec<_>>()
        .join(" ")
        .split_whitespace()
        .collect::<Vec<_>>()
        .join(" ")
}

#[test]
fn the_memory_invariant_is_stated_word_for_word_everywhere() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let invariant = normalized(MEMORY_INVARIANT);
    assert!(invariant.len() > 200, "{invariant}");
    for file in [
        "README.md",
        "ARCHITECTURE.md",
        "docs/flight.md",
        "docs/reliability.md",
        "client/src/scene/mod.rs",
    ] {
        let text =
            std::fs::read_to_string(root.join(file)).unwrap_or_else(|e| panic!("{file}: {e}"));
        assert!(
            normalized(&text).contains(&invariant),
            "{file} does not state the memory invariant word for word:\n{invariant}"
        );
    }
}
