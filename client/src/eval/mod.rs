//! Measuring frames against a reference: screen-space geometric error, crack pixels and
//! colour PSNR. Pure functions of per-pixel data, so every rule is tested on constructed
//! frames; producing that data from the renderer is the caller's.

pub mod accuracy;
pub mod frame;
pub mod levels;
pub mod metrics;
pub mod oracle;
pub mod paper_tables;
pub mod popping;
pub mod session;
pub mod stability;

use crate::method::{CrackFiller, MethodKind};

/// The methods and crack fillers a benchmark runs: shared by `bench accuracy` and
/// `bench stability`.
#[derive(Debug, Clone, PartialEq, clap::Args)]
pub struct Variants {
    /// Methods, comma-separated.
    #[arg(long, value_enum, value_delimiter = ',', default_value = "strip-masks")]
    pub methods: Vec<MethodKind>,
    /// Crack fillers of the methods that use one, comma-separated.
    #[arg(
        long,
        value_enum,
        value_delimiter = ',',
        default_value = "none,skirts,planar-shadow,planar-shadow-paper"
    )]
    pub fillers: Vec<CrackFiller>,
}

impl Default for Variants {
    fn default() -> Variants {
        Variants {
            methods: vec![MethodKind::StripMasks],
            fillers: vec![
                CrackFiller::None,
                CrackFiller::Skirts,
                CrackFiller::PlanarShadow,
                CrackFiller::PlanarShadowPaper,
            ],
        }
    }
}

impl Variants {
    /// Every method with each filler when it uses one (else once, with none), in order.
    pub fn list(&self) -> Vec<(MethodKind, CrackFiller)> {
        let mut out = Vec::new();
        for &method in &self.methods {
            if method.uses_filler() {
                out.extend(self.fillers.iter().map(|&f| (method, f)));
            } else {
                out.push((method, CrackFiller::None));
            }
        }
        out
    }

    /// `method/filler`, or the method alone when it uses no filler.
    pub fn name(method: MethodKind, filler: CrackFiller) -> String {
        method.name_with(filler)
    }
}

/// Parses `NAME=URL` (`--data`).
pub fn parse_named(text: &str) -> Result<(String, String), String> {
    text.split_once('=')
        .filter(|(n, u)| !n.is_empty() && !u.is_empty())
        .map(|(n, u)| (n.to_string(), u.to_string()))
        .ok_or_else(|| {
            format!("{text:?}: expected NAME=URL, e.g. himalaya_4097=http://127.0.0.1:8081")
        })
}

/// A progress bar of `len` steps (hidden when stderr is not a terminal).
pub fn progress(message: &str, len: u64) -> indicatif::ProgressBar {
    let bar = indicatif::ProgressBar::new(len);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{spinner} [{elapsed_precise}] {wide_bar} {pos}/{len} {msg}",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    bar.set_message(message.to_string());
    bar
}
