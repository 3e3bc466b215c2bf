//! Figures in the documents are written by the runs that measured them: every block
//! between `<!-- generated: FILE -->` and `<!-- /generated: FILE -->` in README.md,
//! BENCHMARKS.md, ARCHITECTURE.md and docs/*.md is FILE's text, as
//! `scripts/insert-generated.sh` put it there. A hand edit of either fails here. The
//! hand-kept reading of the evaluation (docs/evaluation-reading.md) restates none of them.

use std::path::Path;

#[test]
fn every_generated_block_is_the_file_it_names() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let mut documents = vec![
        root.join("README.md"),
        root.join("BENCHMARKS.md"),
        root.join("ARCHITECTURE.md"),
    ];
    for entry in std::fs::read_dir(root.join("docs")).expect("docs/") {
        let path = entry.expect("entry").path();
        if path.extension().is_some_and(|e| e == "md") {
            documents.push(path);
        }
    }
    let mut blocks = 0;
    for doc in &documents {
        let text = std::fs::read_to_string(doc).expect("document");
        let mut rest = text.as_str();
        while let Some(at) = rest.find("<!-- generated: ") {
            let after = &rest[at + "<!-- generated: ".len()..];
            let name = after.split(" -->").next().expect("a file name");
            let end = format!("<!-- /generated: {name} -->");
            let body = after
                .split_once(" -->\n")
                .map(|(_, b)| b)
                .and_then(|b| b.split_once(&end))
                .map(|(block, _)| block)
                .unwrap_or_else(|| panic!("{}: {name} is not closed", doc.display()));
            let file = std::fs::read_to_string(root.join(name))
                .unwrap_or_else(|e| panic!("{}: {name}: {e}", doc.display()));
            assert_eq!(
                body.trim_matches('\n'),
                file.trim_matches('\n'),
                "{}: the block differs from {name}; run `bash scripts/insert-generated.sh {} {name}`",
                doc.display(),
                doc.strip_prefix(&root).unwrap_or(doc).display()
            );
            blocks += 1;
            rest = &after[after.find(&end).expect("closed") + end.len()..];
        }
    }
    assert!(
        blocks >= 2,
        "{blocks} generated blocks: the memory and controller tables at least"
    );
}

/// The units after which a number is a measurement (`ms`, `px`, `%`, sizes, `2.3x`).
const UNITS: &[&str] = &[
    "ms",
    "px",
    "%",
    "MiB",
    "KiB",
    "GiB",
    "MB",
    "KB",
    "GB",
    "dB",
    "fps",
    "x",
    "triangles",
    "times",
];

/// Settings, not measurements: the thresholds a method is swept over. (Frame and grid
/// sizes, `640x360`, are let through by the scanner: their `x` is followed by a digit.)
const SETTINGS: &[&str] = &["0.5 px", "1 px", "2 px", "4 px", "8 px", "16 px"];

/// The numbers of `text` that look like measurements, each with its line (1-based): a
/// decimal (`0.147`), a number with thousands separators (`95,600`), or a number followed
/// by one of [`UNITS`] (`46 ms`, `25%`, `2.3x`), unless it is one of [`SETTINGS`]. Text
/// inside backticks is left out: it names columns, knobs and rows.
fn measured_figures(text: &str) -> Vec<(usize, String)> {
    // Backticked spans blanked out (newlines kept, so that lines still count).
    let mut inside = false;
    let prose: Vec<char> = text
        .chars()
        .map(|c| match c {
            '`' => {
                inside = !inside;
                ' '
            }
            '\n' => '\n',
            _ if inside => ' ',
            c => c,
        })
        .collect();
    let word = |c: char| c.is_alphanumeric() || c == '_';
    let mut found = Vec::new();
    let mut i = 0;
    while i < prose.len() {
        let starts =
            prose[i].is_ascii_digit() && (i == 0 || !(word(prose[i - 1]) || prose[i - 1] == '.'));
        if !starts {
            i += 1;
            continue;
        }
        // The number: digits, with `.` or `,` only between digits.
        let mut end = i;
        while end < prose.len()
            && (prose[end].is_ascii_digit()
                || (matches!(prose[end], '.' | ',')
                    && prose.get(end + 1).is_some_and(char::is_ascii_digit)))
        {
            end += 1;
        }
        let number: String = prose[i..end].iter().collect();
        // What follows it, over spaces and at most one line break.
        let mut after = end;
        while after < prose.len() && prose[after] == ' ' {
            after += 1;
        }
        if prose.get(after) == Some(&'\n') {
            after += 1;
            while after < prose.len() && prose[after] == ' ' {
                after += 1;
            }
        }
        let rest: String = prose[after..prose.len().min(after + 12)].iter().collect();
        let unit = UNITS.iter().find(|u| {
            rest.starts_with(**u) && (**u == "%" || !rest[u.len()..].starts_with(|c: char| word(c)))
        });
        let figure = match unit {
            Some(u) if *u == "x" => format!("{number}x"),
            Some(u) => format!("{number} {u}"),
            None => number.clone(),
        };
        let measured = (number.contains('.') || number.contains(',') || unit.is_some())
            && !SETTINGS.contains(&figure.as_str());
        if measured {
            let line = prose[..i].iter().filter(|c| **c == '\n').count() + 1;
            found.push((line, figure));
        }
        i = end;
    }
    found
}

/// The hand-kept reading interprets the generated figures and never restates one, so a
/// re-run cannot leave it stale by a number; and docs/evaluation.md carries it verbatim,
/// as `scripts/evaluate.sh` appends it.
#[test]
fn the_hand_kept_reading_restates_no_figure() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let reading = std::fs::read_to_string(root.join("docs/evaluation-reading.md"))
        .expect("docs/evaluation-reading.md");
    let lines: Vec<&str> = reading.lines().collect();
    let figures: Vec<String> = measured_figures(&reading)
        .into_iter()
        .map(|(line, figure)| {
            format!(
                "docs/evaluation-reading.md:{line}: {figure:?} in {:?}",
                lines.get(line - 1).copied().unwrap_or_default().trim()
            )
        })
        .collect();
    assert!(
        figures.is_empty(),
        "the reading restates measured figures; name the table and column instead:\n{}",
        figures.join("\n")
    );
    let evaluation =
        std::fs::read_to_string(root.join("docs/evaluation.md")).expect("docs/evaluation.md");
    assert!(
        evaluation.contains(&reading),
        "docs/evaluation.md does not carry docs/evaluation-reading.md verbatim; run \
         `TERRAIN_DATA_DIR=../shared/data REUSE=1 bash scripts/evaluate.sh`"
    );
}

#[test]
fn the_figure_scanner_tells_measurements_from_settings() {
    let text = "at 0.147 px mean\nwith 95,600 triangles, 2.3x faster, 46\n  ms and 25%.\n\
                At 1 px, 16 px and 0.5 px on 640x360 with 8 cameras, `0.343 px` and H100.";
    let found: Vec<(usize, String)> = measured_figures(text);
    assert_eq!(
        found,
        [
            (1, "0.147 px".to_string()),
            (2, "95,600 triangles".to_string()),
            (2, "2.3x".to_string()),
            (2, "46 ms".to_string()),
            (3, "25 %".to_string()),
        ]
    );
}
