//! The library's layering: every module imports only from its own layer (without cycles) and
//! the layers below it. The layers are the table in ARCHITECTURE.md (between the
//! `layers:begin` and `layers:end` markers), so the document and the code cannot drift apart.
//!
//! Every `crate::` path in `src/` counts, wherever it stands: `use` lines (also inside
//! braces), qualified paths in code, `#[from]` attributes, type positions and doc comments
//! (doc links resolve against the crate); plain `//` comments do not. `super::` paths that leave their top-level module count as well.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// One import of another top-level module: where it is and what it names.
#[derive(Clone, Debug, PartialEq, Eq, PartialOrd, Ord)]
struct Import {
    from: String,
    to: String,
    file: String,
    line: usize,
}

/// The layer table: layer name and its modules, lowest layer first.
fn parse_layer_table(doc: &str) -> Result<Vec<(String, Vec<String>)>, String> {
    let begin = doc
        .find("<!-- layers:begin -->")
        .ok_or("ARCHITECTURE.md has no `<!-- layers:begin -->` marker")?;
    let end = doc
        .find("<!-- layers:end -->")
        .ok_or("ARCHITECTURE.md has no `<!-- layers:end -->` marker")?;
    let mut layers = Vec::new();
    for row in doc[begin..end].lines() {
        let cells: Vec<&str> = row.trim().trim_matches('|').split('|').collect();
        if cells.len() < 2 || cells[0].trim() == "layer" || cells[0].contains("---") {
            continue;
        }
        // Module names are the back-quoted words of the second cell, outside parentheses.
        let mut cell = String::new();
        let mut depth = 0usize;
        for c in cells[1].chars() {
            match c {
                '(' => depth += 1,
                ')' => depth = depth.saturating_sub(1),
                _ if depth == 0 => cell.push(c),
                _ => {}
            }
        }
        let modules: Vec<String> = cell
            .split('`')
            .skip(1)
            .step_by(2)
            .filter(|m| m.chars().all(|c| c.is_ascii_lowercase() || c == '_'))
            .map(str::to_string)
            .collect();
        layers.push((cells[0].trim().to_string(), modules));
    }
    if layers.is_empty() {
        return Err("the layer table in ARCHITECTURE.md is empty".into());
    }
    Ok(layers)
}

/// Removes `//` comments (doc comments are read apart, by [`doc_text`]) and the contents of
/// string literals, so that neither counts as an import here.
fn strip_comments_and_strings(line: &str) -> String {
    let mut out = String::with_capacity(line.len());
    let mut chars = line.chars().peekable();
    let mut in_string = false;
    while let Some(c) = chars.next() {
        if in_string {
            if c == '\\' {
                chars.next();
            } else if c == '"' {
                in_string = false;
                out.push('"');
            }
            continue;
        }
        if c == '"' {
            in_string = true;
            out.push('"');
            continue;
        }
        if c == '/' && chars.peek() == Some(&'/') {
            break;
        }
        // A char literal holding a quote ('"') must not open a string.
        if c == '\'' {
            let rest: String = chars.clone().take(3).collect();
            if rest.starts_with("\"'") || rest.starts_with("\\\"'") {
                for _ in 0..rest.find('\'').unwrap_or(0) + 1 {
                    chars.next();
                }
                continue;
            }
        }
        out.push(c);
    }
    out
}

/// The text of a doc comment line (`///` or `//!`), else `None`.
fn doc_text(line: &str) -> Option<String> {
    let t = line.trim_start();
    (t.starts_with("///") || t.starts_with("//!")).then(|| t[3..].to_string())
}

/// The top-level modules named by `crate::` paths in one line of code. `group` carries an
/// unfinished `crate::{ ... }` group over to the next lines.
fn crate_targets(code: &str, group: &mut Option<usize>) -> Vec<String> {
    let mut out = Vec::new();
    let mut rest = code;
    if let Some(depth) = group.as_mut() {
        // Inside `use crate::{ ... }`: the first identifier of each item at depth 1.
        let mut item_start = true;
        let mut ident = String::new();
        for c in rest.chars() {
            if c.is_alphanumeric() || c == '_' {
                ident.push(c);
                continue;
            }
            if !ident.is_empty() {
                if item_start && *depth == 1 && ident != "self" {
                    out.push(ident.clone());
                }
                item_start = false;
                ident.clear();
            }
            match c {
                '{' => {
                    *depth += 1;
                    item_start = true;
                }
                '}' => {
                    *depth -= 1;
                    if *depth == 0 {
                        break;
                    }
                }
                ',' if *depth == 1 => item_start = true,
                _ => {}
            }
        }
        if !ident.is_empty() && item_start && *depth == 1 {
            out.push(ident);
        }
        if *depth == 0 {
            *group = None;
        }
        return out;
    }
    while let Some(pos) = rest.find("crate::") {
        let before = rest[..pos].chars().last();
        rest = &rest[pos + "crate::".len()..];
        if before.is_some_and(|c| c.is_alphanumeric() || c == '_' || c == '$') {
            continue;
        }
        if let Some(after) = rest.strip_prefix('{') {
            let mut depth = Some(1);
            out.extend(crate_targets(after, &mut depth));
            if depth.is_some() {
                *group = depth;
                return out;
            }
            continue;
        }
        let ident: String = rest
            .chars()
            .take_while(|c| c.is_alphanumeric() || *c == '_')
            .collect();
        if !ident.is_empty() {
            out.push(ident);
        }
    }
    out
}

/// `super::` chains that leave the file's top-level module: the module they reach.
fn super_targets(code: &str, depth_in_module: usize) -> Vec<String> {
    let mut out = Vec::new();
    let mut rest = code;
    while let Some(pos) = rest.find("super::") {
        let before = rest[..pos].chars().last();
        rest = &rest[pos..];
        if before.is_some_and(|c| c.is_alphanumeric() || c == '_') {
            rest = &rest["super::".len()..];
            continue;
        }
        let mut ups = 0;
        while let Some(r) = rest.strip_prefix("super::") {
            ups += 1;
            rest = r;
        }
        if ups > depth_in_module {
            let ident: String = rest
                .chars()
                .take_while(|c| c.is_alphanumeric() || *c == '_')
                .collect();
            if !ident.is_empty() {
                out.push(ident);
            }
        }
    }
    out
}

/// The top-level module of a file under `src/` and how deep inside it the file's own module is
/// (`io/mod.rs` and `io.rs`: 0, `io/tum.rs`: 1), or `None` for the crate root files.
fn module_of(rel: &Path) -> Option<(String, usize)> {
    let parts: Vec<String> = rel
        .iter()
        .map(|p| p.to_string_lossy().into_owned())
        .collect();
    let top = parts.first()?.trim_end_matches(".rs").to_string();
    if parts.len() == 1 && (top == "lib" || top == "main") {
        return None;
    }
    let last = parts.last()?;
    let depth = parts.len() - 1 - usize::from(last == "mod.rs");
    Some((top, depth))
}

/// Every import of another top-level module in the given files (`(path under src, text)`).
/// Test modules (`#[cfg(test)]` blocks) count too: they are part of the module.
fn imports(files: &[(PathBuf, String)], modules: &BTreeSet<String>) -> Vec<Import> {
    let mut out = Vec::new();
    for (rel, text) in files {
        let Some((from, depth)) = module_of(rel) else {
            continue;
        };
        let mut group = None;
        for (i, line) in text.lines().enumerate() {
            let code = strip_comments_and_strings(line);
            let mut targets = crate_targets(&code, &mut group);
            // Doc links resolve against the crate as imports do, so they count as edges.
            if let Some(doc) = doc_text(line) {
                targets.extend(crate_targets(&doc.replace('"', " "), &mut None));
            }
            targets.extend(super_targets(&code, depth));
            for to in targets {
                if to != from && modules.contains(&to) {
                    out.push(Import {
                        from: from.clone(),
                        to,
                        file: rel.display().to_string(),
                        line: i + 1,
                    });
                }
            }
        }
    }
    out.sort();
    out
}

/// Upward imports and cycles, as messages (empty when the layering holds).
fn violations(layers: &[(String, Vec<String>)], imports: &[Import]) -> Vec<String> {
    let layer_of: BTreeMap<&str, usize> = layers
        .iter()
        .enumerate()
        .flat_map(|(k, (_, ms))| ms.iter().map(move |m| (m.as_str(), k)))
        .collect();
    let mut out = Vec::new();
    let mut edges: BTreeMap<&str, BTreeSet<&str>> = BTreeMap::new();
    for imp in imports {
        let (Some(&a), Some(&b)) = (
            layer_of.get(imp.from.as_str()),
            layer_of.get(imp.to.as_str()),
        ) else {
            continue;
        };
        if b > a {
            out.push(format!(
                "src/{}:{}: `{}` ({}) imports `{}` from a higher layer ({})",
                imp.file, imp.line, imp.from, layers[a].0, imp.to, layers[b].0
            ));
        }
        edges
            .entry(imp.from.as_str())
            .or_default()
            .insert(imp.to.as_str());
    }
    // Cycles: a module that reaches itself through the import graph.
    for &start in edges.keys() {
        let mut stack: Vec<Vec<&str>> = vec![vec![start]];
        let mut seen = BTreeSet::new();
        while let Some(path) = stack.pop() {
            let last = path[path.len() - 1];
            for &next in edges.get(last).into_iter().flatten() {
                if next == start {
                    let mut cycle = path.clone();
                    cycle.push(start);
                    // Report each cycle once, from its smallest module.
                    if cycle.iter().all(|m| *m >= start) {
                        out.push(format!("import cycle: {}", cycle.join(" -> ")));
                    }
                } else if seen.insert(next) {
                    let mut p = path.clone();
                    p.push(next);
                    stack.push(p);
                }
            }
        }
    }
    out
}

fn rust_files(dir: &Path, root: &Path, out: &mut Vec<(PathBuf, String)>) {
    let mut entries: Vec<_> = std::fs::read_dir(dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|e| e.expect("directory entry").path())
        .collect();
    entries.sort();
    for p in entries {
        if p.is_dir() {
            rust_files(&p, root, out);
        } else if p.extension().is_some_and(|e| e == "rs") {
            let text =
                std::fs::read_to_string(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
            let rel = p.strip_prefix(root).expect("under src").to_path_buf();
            out.push((rel, text));
        }
    }
}

#[test]
fn modules_import_only_from_their_layer_or_below_and_form_no_cycle() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let doc = std::fs::read_to_string(root.join("ARCHITECTURE.md")).expect("ARCHITECTURE.md");
    let layers = parse_layer_table(&doc).unwrap_or_else(|e| panic!("{e}"));
    let mut files = Vec::new();
    rust_files(&root.join("src"), &root.join("src"), &mut files);

    // Every top-level module of src/ is placed in exactly one layer, and every module in the
    // table exists.
    let on_disk: BTreeSet<String> = files
        .iter()
        .filter_map(|(rel, _)| module_of(rel).map(|(m, _)| m))
        .collect();
    let mut placed = BTreeSet::new();
    for (_, ms) in &layers {
        for m in ms {
            assert!(placed.insert(m.clone()), "`{m}` is in two layers");
        }
    }
    assert_eq!(
        on_disk, placed,
        "the modules in src/ (left) and in ARCHITECTURE.md's layer table (right) differ"
    );

    let found = imports(&files, &on_disk);
    assert!(
        found.len() > 100,
        "only {} cross-module imports found: the parser is broken",
        found.len()
    );
    let bad = violations(&layers, &found);
    assert!(bad.is_empty(), "layering violated:\n{}", bad.join("\n"));
}

/// The checker itself: an upward import, a cycle within a layer, a grouped `use`, a `#[from]`
/// attribute, a qualified path, a `super::` that leaves its module, a doc link, and what must
/// not count (a plain comment, a string).
#[test]
fn the_checker_finds_upward_imports_and_cycles() {
    let layers = vec![
        ("foundation".to_string(), vec!["geometry".to_string()]),
        (
            "algorithms".to_string(),
            vec!["odometry".to_string(), "graph".to_string()],
        ),
        ("systems".to_string(), vec!["slam".to_string()]),
    ];
    let modules: BTreeSet<String> = ["geometry", "odometry", "graph", "slam"]
        .iter()
        .map(|s| s.to_string())
        .collect();
    let file = |p: &str, t: &str| (PathBuf::from(p), t.to_string());
    let files = vec![
        file(
            "geometry/se3.rs",
            "//! See [`crate::slam`].\n// not crate::graph\nlet s = \"crate::slam\";\nuse crate::{\n    odometry::X,\n};",
        ),
        file("odometry/mod.rs", "fn f(g: crate::graph::G) {}"),
        file(
            "graph/solver.rs",
            "#[error(transparent)]\nE(#[from] super::super::odometry::E),",
        ),
        file("slam/mod.rs", "use crate::{geometry::Se3, odometry};"),
    ];
    let found = imports(&files, &modules);
    let pairs: Vec<(&str, &str, usize)> = found
        .iter()
        .map(|i| (i.from.as_str(), i.to.as_str(), i.line))
        .collect();
    assert_eq!(
        pairs,
        vec![
            ("geometry", "odometry", 5),
            ("geometry", "slam", 1),
            ("graph", "odometry", 2),
            ("odometry", "graph", 1),
            ("slam", "geometry", 1),
            ("slam", "odometry", 1),
        ]
    );
    let bad = violations(&layers, &found);
    assert_eq!(bad.len(), 4, "{bad:?}");
    assert!(bad[0].contains("src/geometry/se3.rs:5") && bad[0].contains("higher layer"));
    assert!(bad[1].contains("src/geometry/se3.rs:1") && bad[1].contains("higher layer"));
    assert_eq!(bad[2], "import cycle: geometry -> slam -> geometry");
    assert_eq!(bad[3], "import cycle: graph -> odometry -> graph");
    // Without the upward import and the cycle, nothing is reported.
    let clean: Vec<Import> = found
        .into_iter()
        .filter(|i| i.from != "geometry" && i.from != "graph")
        .collect();
    assert!(violations(&layers, &clean).is_empty());
}
