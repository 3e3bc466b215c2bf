//! The client's modules depend on each other without a loop, at every depth (the
//! top-level modules, and the modules of each folder among themselves), and the renderer
//! names no level-of-detail method: read from the sources, so a new import that closes a
//! loop fails here.
//!
//! `cargo test -p terrain-client --test modules -- --nocapture` prints the module graph.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

fn src() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("src")
}

/// Every `.rs` file under `dir`.
fn sources(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for entry in std::fs::read_dir(dir).expect("read src") {
        let path = entry.expect("entry").path();
        if path.is_dir() {
            out.extend(sources(&path));
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
    out
}

/// The code of a file without its comments (line comments and doc comments).
fn code(path: &Path) -> String {
    std::fs::read_to_string(path)
        .expect("read source")
        .lines()
        .map(|line| match line.find("//") {
            Some(at) => &line[..at],
            None => line,
        })
        .collect::<Vec<_>>()
        .join("\n")
}

/// The module a file is (`["render", "frame"]` for `src/render/frame.rs`, `["eval"]` for
/// `src/eval/mod.rs`, `[]` for `lib.rs` and `main.rs`).
fn module_of(path: &Path) -> Vec<String> {
    let relative = path.strip_prefix(src()).expect("under src");
    let mut parts: Vec<String> = relative
        .components()
        .map(|c| c.as_os_str().to_string_lossy().into_owned())
        .collect();
    let file = parts.pop().expect("a file name");
    let stem = file.trim_end_matches(".rs");
    if !matches!(stem, "mod" | "lib" | "main") {
        parts.push(stem.to_string());
    }
    parts
}

fn is_ident(c: char) -> bool {
    c.is_ascii_alphanumeric() || c == '_'
}

/// The `::`-separated identifiers at the start of `text`, and what follows them: a `{` group
/// is returned unread.
fn path_at(text: &str) -> (Vec<String>, &str) {
    let mut parts = Vec::new();
    let mut rest = text;
    loop {
        let name: String = rest.chars().take_while(|c| is_ident(*c)).collect();
        if name.is_empty() {
            break;
        }
        rest = &rest[name.len()..];
        parts.push(name);
        match rest.strip_prefix("::") {
            Some(after) => rest = after,
            None => break,
        }
    }
    (parts, rest)
}

/// The comma-separated items of the `{...}` group at the start of `text`, nested groups
/// kept whole.
fn group_items(text: &str) -> Vec<&str> {
    let mut items = Vec::new();
    let (mut depth, mut from) = (0usize, 1usize);
    for (at, c) in text.char_indices() {
        match c {
            '{' => depth += 1,
            '}' => {
                depth -= 1;
                if depth == 0 {
                    items.push(&text[from..at]);
                    break;
                }
            }
            ',' if depth == 1 => {
                items.push(&text[from..at]);
                from = at + 1;
            }
            _ => {}
        }
    }
    items
}

/// Every path `text` (the code of module `module`) names through `crate::`, `super::` or
/// `self::`, resolved to a path from the crate root, groups expanded
/// (`use super::{a::B, c}` in `eval::x` names `eval::a::B` and `eval::c`).
fn references(text: &str, module: &[String]) -> BTreeSet<Vec<String>> {
    let mut out = BTreeSet::new();
    let expand = |base: Vec<String>, rest: &str, out: &mut BTreeSet<Vec<String>>| {
        let mut pending = vec![(base, rest.to_string())];
        while let Some((base, rest)) = pending.pop() {
            let (parts, after) = path_at(&rest);
            let mut full = base.clone();
            full.extend(parts);
            if after.starts_with('{') {
                for item in group_items(after) {
                    pending.push((full.clone(), item.trim().to_string()));
                }
            } else {
                out.insert(full);
            }
        }
    };
    for (at, _) in text.match_indices("::") {
        // The first segment: `crate`, `self` or one or more `super`s.
        let head_start = text[..at]
            .rfind(|c: char| !(is_ident(c) || c == ':'))
            .map_or(0, |i| i + 1);
        let head = &text[head_start..at];
        let mut rest = &text[at + 2..];
        let base = match head {
            "crate" => Vec::new(),
            "self" => module.to_vec(),
            // `super` names the module's parent (from `eval/levels.rs`, `eval`; from
            // `eval/mod.rs`, the root), each further `super` the parent's.
            "super" => {
                let mut base = module.to_vec();
                base.pop();
                while let Some(after) = rest.strip_prefix("super::") {
                    base.pop();
                    rest = after;
                }
                base
            }
            _ => continue,
        };
        expand(base, rest, &mut out);
    }
    out
}

/// For each folder of modules (the crate root, `eval`, `render`, ...), which of its
/// children import which: an import from `render::frame` of `render::offscreen::f` is the
/// edge `frame -> offscreen` in the folder `render`; one of `crate::page::X` from
/// `eval::levels` is `eval -> page` in the root.
fn graphs() -> BTreeMap<String, BTreeMap<String, BTreeSet<String>>> {
    let mut graphs: BTreeMap<String, BTreeMap<String, BTreeSet<String>>> = BTreeMap::new();
    for path in sources(&src()) {
        let module = module_of(&path);
        for target in references(&code(&path), &module) {
            let common = module
                .iter()
                .zip(&target)
                .take_while(|(a, b)| a == b)
                .count();
            // A module naming its own items, an ancestor or a descendant: no edge.
            let (Some(from), Some(to)) = (module.get(common), target.get(common)) else {
                continue;
            };
            // `crate::NAME` where NAME is an item of the root, not a module, has no file.
            let folder = module[..common].join("::");
            graphs
                .entry(folder)
                .or_default()
                .entry(from.clone())
                .or_default()
                .insert(to.clone());
        }
    }
    // Only children that are modules: an item named in a folder (`super::CONST`) is no node.
    let modules: BTreeSet<Vec<String>> = sources(&src()).iter().map(|p| module_of(p)).collect();
    for (folder, graph) in &mut graphs {
        let prefix: Vec<String> = if folder.is_empty() {
            Vec::new()
        } else {
            folder.split("::").map(String::from).collect()
        };
        let is_module = |name: &String| {
            let mut path = prefix.clone();
            path.push(name.clone());
            modules.contains(&path)
        };
        graph.retain(|from, _| is_module(from));
        for uses in graph.values_mut() {
            uses.retain(|to| is_module(to));
        }
    }
    graphs
}

/// A loop through `graph`, if there is one.
fn find_loop(graph: &BTreeMap<String, BTreeSet<String>>) -> Option<Vec<String>> {
    fn visit(
        node: &str,
        graph: &BTreeMap<String, BTreeSet<String>>,
        path: &mut Vec<String>,
        done: &mut BTreeSet<String>,
    ) -> Option<Vec<String>> {
        if let Some(at) = path.iter().position(|n| n == node) {
            let mut cycle = path[at..].to_vec();
            cycle.push(node.to_string());
            return Some(cycle);
        }
        if done.contains(node) {
            return None;
        }
        path.push(node.to_string());
        for next in graph.get(node).into_iter().flatten() {
            if let Some(cycle) = visit(next, graph, path, done) {
                return Some(cycle);
            }
        }
        path.pop();
        done.insert(node.to_string());
        None
    }
    let mut done = BTreeSet::new();
    for node in graph.keys() {
        if let Some(cycle) = visit(node, graph, &mut Vec::new(), &mut done) {
            return Some(cycle);
        }
    }
    None
}

#[test]
fn no_two_modules_import_each_other_directly_or_in_a_loop_at_any_depth() {
    let graphs = graphs();
    for (folder, graph) in &graphs {
        for (module, uses) in graph {
            println!(
                "{}{module} -> {}",
                if folder.is_empty() {
                    String::new()
                } else {
                    format!("{folder}::")
                },
                uses.iter().cloned().collect::<Vec<_>>().join(", ")
            );
        }
    }
    let root = &graphs[""];
    assert!(root.len() > 10, "the modules were found: {root:?}");
    assert!(
        root["scene"].contains("render"),
        "the reading of imports works"
    );
    assert!(
        graphs["render"]["frame"].contains("gpu"),
        "the reading of imports inside a folder works: {:?}",
        graphs["render"]
    );
    let loops: Vec<String> = graphs
        .iter()
        .filter_map(|(folder, graph)| {
            find_loop(graph).map(|cycle| format!("in {folder:?}: {}", cycle.join(" -> ")))
        })
        .collect();
    assert!(loops.is_empty(), "modules import each other: {loops:#?}");
}

#[test]
fn the_loop_finder_finds_a_loop() {
    let mut graph: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    graph.entry("a".into()).or_default().insert("b".into());
    graph.entry("b".into()).or_default().insert("c".into());
    assert_eq!(find_loop(&graph), None);
    graph.entry("c".into()).or_default().insert("a".into());
    assert_eq!(
        find_loop(&graph),
        Some(vec!["a".into(), "b".into(), "c".into(), "a".into()])
    );
}

#[test]
fn references_are_resolved_from_the_crate_root() {
    let module = |m: &str| m.split("::").map(String::from).collect::<Vec<_>>();
    let found = references(
        "use crate::{scene::Scene, render};\nlet x = crate::eval::f();\nuse super::{a::B, c};\nsuper::super::page::decide();\nself::inner::g();",
        &module("eval::levels"),
    );
    let expected: BTreeSet<Vec<String>> = [
        "scene::Scene",
        "render",
        "eval::f",
        "eval::a::B",
        "eval::c",
        "page::decide",
        "eval::levels::inner::g",
    ]
    .iter()
    .map(|p| module(p))
    .collect();
    assert_eq!(found, expected);
    // From `mod.rs`, `super` is the folder's parent.
    assert_eq!(
        references("super::page::X", &module("eval")),
        [module("page::X")].into()
    );
}

#[test]
fn no_file_of_the_renderer_names_a_method() {
    let words = [
        "strip_masks",
        "StripMasks",
        "geomipmap",
        "GeoMipMap",
        "MethodKind",
        "crate::method",
        "CrackFiller",
        "skirt",
        "shadow",
    ];
    let mut found = Vec::new();
    for path in sources(&src().join("render")) {
        let text = code(&path);
        for word in words {
            if text.contains(word) {
                found.push(format!("{} names {word}", path.display()));
            }
        }
    }
    assert!(found.is_empty(), "{found:#?}");
}

#[test]
fn the_scene_names_the_method_kind_only_to_build_the_method() {
    let text: String = sources(&src().join("scene"))
        .iter()
        .map(|path| code(path))
        .collect::<Vec<_>>()
        .join("\n");
    let uses: Vec<&str> = text
        .lines()
        .filter(|l| l.contains("MethodKind"))
        .map(str::trim)
        .collect();
    // The import, and the field of the configuration the method is built from.
    assert!(
        uses.iter().all(|l| l.starts_with("use ")
            || l.starts_with("pub method: MethodKind")
            || l.starts_with("method: MethodKind::default()")),
        "{uses:#?}"
    );
}

/// The lines of a file before its unit tests (`#[cfg(test)]` at the start of a line).
fn lines_before_tests(text: &str) -> usize {
    text.lines()
        .take_while(|line| !line.starts_with("#[cfg(test)]"))
        .count()
}

/// A reader can hold a file: none is over 900 lines before its unit tests.
#[test]
fn no_file_is_over_900_lines_before_its_tests() {
    const LIMIT: usize = 900;
    let mut long = Vec::new();
    let files = sources(&src());
    assert!(files.len() > 30, "the sources were found: {}", files.len());
    for path in files {
        let text = std::fs::read_to_string(&path).expect("read source");
        let n = lines_before_tests(&text);
        if n > LIMIT {
            long.push(format!("{} ({n} lines)", path.display()));
        }
    }
    assert!(
        long.is_empty(),
        "over {LIMIT} lines before the tests: {long:#?}"
    );
}

#[test]
fn the_line_counter_stops_at_the_tests() {
    assert_eq!(lines_before_tests("a\nb\n#[cfg(test)]\nmod tests {}\n"), 2);
    assert_eq!(lines_before_tests("a\nb\nc\n"), 3);
}

/// Each level-of-detail method has one folder under `method/` (its selection and its GPU
/// part), and no file elsewhere is named after one.
#[test]
fn each_method_has_one_folder_and_no_file_elsewhere_is_named_after_one() {
    let methods = [
        "strip_masks",
        "geomipmap",
        "projected_grid",
        "quadtree_patches",
    ];
    let method_dir = src().join("method");
    for name in methods {
        assert!(
            method_dir.join(name).join("mod.rs").is_file(),
            "method/{name}/mod.rs is missing"
        );
    }
    let words = ["geomipmap", "mipmap", "grid", "patch", "strip_mask"];
    let strays: Vec<String> = sources(&src())
        .into_iter()
        .filter(|p| !p.starts_with(&method_dir))
        .filter(|p| {
            let stem = p.file_stem().unwrap_or_default().to_string_lossy();
            words.iter().any(|w| stem.contains(w))
        })
        .map(|p| p.display().to_string())
        .collect();
    assert!(
        strays.is_empty(),
        "files named after a method outside method/: {strays:#?}"
    );
    let loose: Vec<String> = std::fs::read_dir(&method_dir)
        .expect("read method/")
        .map(|e| e.expect("entry").path())
        .filter(|p| p.is_dir() && !methods.iter().any(|m| p.ends_with(m)))
        .map(|p| p.display().to_string())
        .collect();
    assert!(
        loose.is_empty(),
        "folders under method/ that are no method: {loose:#?}"
    );
}
