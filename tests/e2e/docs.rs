//! Figures in the documents are written by the runs that measured them: every block
//! between `<!-- generated: FILE -->` and `<!-- /generated: FILE -->` in README.md,
//! BENCHMARKS.md, ARCHITECTURE.md and docs/*.md is FILE's text, as
//! `scripts/insert-generated.sh` put it there. A hand edit of either fails here.

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
