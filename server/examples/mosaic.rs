//! Writes a larger DEM made of four mirrored copies of a 16-bit greyscale PNG, in bounded
//! memory (see `benches/common/mosaic.rs`, which the builder's memory benchmark uses):
//!
//! ```text
//! cargo run --release -p terrain-server --example mosaic -- SOURCE.png OUT.png
//! ```
//!
//! From himalaya_4097 it makes the 8193 x 8193 input of `benches/build_memory.rs`.

#[path = "../benches/common/mosaic.rs"]
mod mosaic;

use anyhow::Context;
use std::path::PathBuf;

fn main() -> anyhow::Result<()> {
    let mut args = std::env::args_os().skip(1).map(PathBuf::from);
    let (Some(source), Some(out)) = (args.next(), args.next()) else {
        anyhow::bail!("usage: mosaic SOURCE.png OUT.png");
    };
    let [width, height] = mosaic::write_mirrored(&source, &out)
        .with_context(|| format!("cannot make a mosaic of {}", source.display()))?;
    println!("wrote {} ({width} x {height} samples)", out.display());
    Ok(())
}
