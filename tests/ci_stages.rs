//! Every test runs in exactly one CI stage (`.ci/run`), and the names say which:
//!
//! | stage | tests | command |
//! |---|---|---|
//! | tests | not ignored: need neither a GPU nor `../shared/data` | `cargo test --workspace` |
//! | GPU tests | `gpu_*`, `#[ignore = "needs a GPU adapter"]` | `cargo test --workspace --tests -- --ignored gpu_` |
//! | real-data tests | ignored with a reason naming `../shared/data` | `cargo test --workspace --tests -- --ignored --skip gpu_ --skip known_gap_ --skip manual_` |
//! | none | `known_gap_*` (unmet targets), `manual_*` (benchmarks, file writers) | by hand |
//! | openni2 feature | `#[cfg(feature = "openni2")]` tests of `live` | `cargo test --lib --features openni2 live::` |
//!
//! The Python package's tests (`python/tests`, pytest) run in the stage `python` only.
//!
//! libtest filters match substrings of the full test path, so this test reads every `#[test]`
//! in `src/`, `tests/` and `viewer/`, and checks that each ignored test carries the marker of
//! its stage and no other, that a test calling the GPU test helper (`rgbid::gpu::test_gpu`, the
//! viewer's `gpu_render_state`) is ignored as needing a GPU adapter, and that `.ci/run` runs
//! the stages with these filters.

use std::path::{Path, PathBuf};

const ROOT: &str = env!("CARGO_MANIFEST_DIR");
const GPU_REASON: &str = "needs a GPU adapter";
const DATA_REASON: &str = "../shared/data";
/// Calls that obtain a GPU adapter in a test.
const GPU_HELPERS: [&str; 2] = ["test_gpu(", "gpu_render_state("];
/// Ways to a GPU that bypass the helper (and with it the skip-or-fail rule).
const GPU_BYPASSES: [&str; 3] = ["any_gpu(", "BackendChoice::Gpu", "create_render_state("];
/// The markers the CI filters use, in the order of [`Stage`]'s marked variants.
const MARKERS: [&str; 3] = ["gpu_", "known_gap_", "manual_"];
/// The filters `.ci/run` must use.
const CI_FILTERS: [&str; 2] = [
    "-- --ignored gpu_",
    "-- --ignored --skip gpu_ --skip known_gap_ --skip manual_",
];

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Stage {
    Tests,
    Gpu,
    RealData,
    KnownGap,
    Manual,
}

impl Stage {
    fn marker(self) -> Option<&'static str> {
        match self {
            Stage::Gpu => Some(MARKERS[0]),
            Stage::KnownGap => Some(MARKERS[1]),
            Stage::Manual => Some(MARKERS[2]),
            Stage::Tests | Stage::RealData => None,
        }
    }
}

struct TestFn {
    /// `file:line: name`, for messages.
    place: String,
    /// The lines of its body in its file (0-based, inclusive).
    lines: (usize, usize),
    /// What libtest filters match: the module path (for `src/` files) and the name.
    full_name: String,
    name: String,
    ignore: Option<String>,
    body: String,
}

/// Whether `code` calls one of [`GPU_HELPERS`] (as a whole name: `no_test_gpu(` does not count).
fn calls_gpu_helper(code: &str) -> bool {
    GPU_HELPERS.iter().any(|h| {
        code.match_indices(h).any(|(at, _)| {
            !code[..at]
                .chars()
                .next_back()
                .is_some_and(|c| c.is_alphanumeric() || c == '_')
        })
    })
}

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for e in entries.flatten() {
        let p = e.path();
        if p.is_dir() {
            if p.file_name().is_some_and(|n| n != "snapshots") {
                rust_files(&p, out);
            }
        } else if p.extension().is_some_and(|x| x == "rs") {
            out.push(p);
        }
    }
}

/// The module path of a library source file (`src/io/undistort_gpu.rs` -> `io::undistort_gpu`);
/// empty for integration tests, whose file name is not part of a test's name.
fn module_path(rel: &str) -> String {
    let inner = rel
        .strip_prefix("viewer/src/")
        .or_else(|| rel.strip_prefix("src/"));
    let Some(inner) = inner else {
        return String::new();
    };
    let inner = inner.trim_end_matches(".rs");
    let parts: Vec<&str> = inner
        .split('/')
        .filter(|p| !matches!(*p, "mod" | "lib" | "main"))
        .collect();
    parts.join("::")
}

fn ignore_reason(attr: &str) -> Option<String> {
    let a = attr.trim();
    if a == "#[ignore]" {
        return Some(String::new());
    }
    if a.starts_with("#[ignore") {
        let (first, last) = (a.find('"')?, a.rfind('"')?);
        return Some(a[first + 1..last.max(first + 1)].to_string());
    }
    None
}

fn tests_in(path: &Path) -> Vec<TestFn> {
    let text = std::fs::read_to_string(path).expect("read source");
    let rel = path
        .strip_prefix(ROOT)
        .expect("under the crate")
        .to_string_lossy()
        .replace('\\', "/");
    let lines: Vec<&str> = text.lines().collect();
    // Inline modules (`mod tests {`) are part of a unit test's path.
    let mods: Vec<String> = lines
        .iter()
        .filter_map(|l| {
            let t = l
                .trim_start()
                .strip_prefix("pub ")
                .unwrap_or(l.trim_start());
            let name = t.strip_prefix("mod ")?.strip_suffix(" {")?;
            Some(name.to_string())
        })
        .collect();
    let module = module_path(&rel);
    let mut found = Vec::new();
    for (i, line) in lines.iter().enumerate() {
        if line.trim() != "#[test]" {
            continue;
        }
        let mut ignore = None;
        // Attributes before and after `#[test]`, up to the `fn` line.
        for prev in lines[..i].iter().rev() {
            let t = prev.trim();
            if !(t.starts_with("#[") || t.starts_with("///")) {
                break;
            }
            ignore = ignore.or(ignore_reason(t));
        }
        let mut j = i + 1;
        while j < lines.len() && !lines[j].trim_start().starts_with("fn ") {
            let t = lines[j].trim();
            assert!(
                t.starts_with("#[") || t.starts_with("//"),
                "{rel}:{}: unexpected line between #[test] and its fn: {t}",
                j + 1
            );
            ignore = ignore.or(ignore_reason(t));
            j += 1;
        }
        assert!(j < lines.len(), "{rel}:{}: #[test] without a fn", i + 1);
        let fn_line = lines[j];
        let name: String = fn_line.trim_start()["fn ".len()..]
            .chars()
            .take_while(|c| c.is_alphanumeric() || *c == '_')
            .collect();
        let indent = &fn_line[..fn_line.len() - fn_line.trim_start().len()];
        let end = (j + 1..lines.len())
            .find(|&k| lines[k] == format!("{indent}}}"))
            .unwrap_or(lines.len() - 1);
        let body = lines[j..=end].join("\n");
        let mut path_parts: Vec<&str> = Vec::new();
        if !module.is_empty() {
            path_parts.push(&module);
        }
        path_parts.extend(mods.iter().map(String::as_str));
        path_parts.push(&name);
        found.push(TestFn {
            place: format!("{rel}:{}: {name}", j + 1),
            lines: (j, end),
            full_name: path_parts.join("::"),
            name,
            ignore,
            body,
        });
    }
    found
}

fn source_files() -> Vec<PathBuf> {
    let mut files = Vec::new();
    for dir in ["src", "tests", "viewer/src", "viewer/tests"] {
        rust_files(&Path::new(ROOT).join(dir), &mut files);
    }
    files.sort();
    let me = Path::new(ROOT).join("tests/ci_stages.rs");
    files.retain(|f| *f != me);
    files
}

fn all_tests() -> Vec<TestFn> {
    source_files().iter().flat_map(|f| tests_in(f)).collect()
}

/// Calls of the GPU test helper outside the body of a GPU (or manual) test and outside the
/// helpers themselves: a test reaching the GPU through another function would escape the
/// check that it is ignored.
fn stray_gpu_helper_calls(path: &Path) -> Vec<String> {
    let text = std::fs::read_to_string(path).expect("read source");
    let lines: Vec<&str> = text.lines().collect();
    let tests = tests_in(path);
    let in_gpu_test = |k: usize| {
        tests.iter().any(|t| {
            (t.lines.0..=t.lines.1).contains(&k)
                && matches!(stage(t), Ok(Stage::Gpu) | Ok(Stage::Manual))
        })
    };
    // The helpers' own definitions (`fn test_gpu(`, the viewer's `fn gpu_render_state(`).
    let mut helper_spans = Vec::new();
    for (k, l) in lines.iter().enumerate() {
        let t = l.trim_start();
        let t = t.strip_prefix("pub ").unwrap_or(t);
        if GPU_HELPERS
            .iter()
            .any(|h| t.starts_with(&format!("fn {h}")))
        {
            let indent = &l[..l.len() - l.trim_start().len()];
            let end = (k + 1..lines.len())
                .find(|&e| lines[e] == format!("{indent}}}"))
                .unwrap_or(lines.len() - 1);
            helper_spans.push((k, end));
        }
    }
    lines
        .iter()
        .enumerate()
        .filter(|(k, l)| {
            let code = l.trim_start();
            !code.starts_with("//")
                && calls_gpu_helper(code)
                && !helper_spans.iter().any(|(a, b)| (a..=b).contains(&k))
                && !in_gpu_test(*k)
        })
        .map(|(k, l)| {
            let rel = path.strip_prefix(ROOT).unwrap_or(path);
            format!("{}:{}: {}", rel.display(), k + 1, l.trim())
        })
        .collect()
}

/// The stage a test runs in, or why it is misfiled.
fn stage(t: &TestFn) -> Result<Stage, String> {
    let calls_gpu = calls_gpu_helper(&t.body);
    if let Some(b) = GPU_BYPASSES.iter().find(|b| t.body.contains(*b)) {
        return Err(format!(
            "reaches the GPU through {b}: use rgbid::gpu::test_gpu (and name it gpu_)"
        ));
    }
    let Some(reason) = &t.ignore else {
        if calls_gpu {
            return Err(format!(
                "calls the GPU test helper but is not #[ignore = \"{GPU_REASON}\"]"
            ));
        }
        if MARKERS.iter().any(|m| t.name.starts_with(m)) {
            return Err("has a CI stage marker as its prefix but is not ignored".into());
        }
        return Ok(Stage::Tests);
    };
    let stage = if t.name.starts_with(MARKERS[0]) {
        if reason != GPU_REASON {
            return Err(format!("a gpu_ test must be #[ignore = \"{GPU_REASON}\"]"));
        }
        Stage::Gpu
    } else if t.name.starts_with(MARKERS[1]) {
        if !reason.starts_with("known gap") {
            return Err("a known_gap_ test's ignore reason must start with \"known gap\"".into());
        }
        Stage::KnownGap
    } else if t.name.starts_with(MARKERS[2]) {
        Stage::Manual
    } else if reason.contains(DATA_REASON) {
        Stage::RealData
    } else {
        return Err(format!(
            "ignored, but neither gpu_, known_gap_ nor manual_, and its reason does not name \
             {DATA_REASON}: CI would run it in the real-data stage"
        ));
    };
    if calls_gpu && !reason.contains(GPU_REASON) {
        return Err(format!(
            "calls the GPU test helper, but its ignore reason {reason:?} lacks \"{GPU_REASON}\""
        ));
    }
    if !calls_gpu && reason.contains(GPU_REASON) {
        return Err(format!(
            "its ignore reason says \"{GPU_REASON}\", but it does not call the GPU test helper \
             (rgbid::gpu::test_gpu)"
        ));
    }
    if stage == Stage::RealData && calls_gpu {
        return Err("a real-data test that needs a GPU runs in no stage".into());
    }
    for m in MARKERS {
        if t.full_name.contains(m) != (stage.marker() == Some(m)) {
            return Err(format!(
                "its path {} {} the filter {m:?}",
                t.full_name,
                if stage.marker() == Some(m) {
                    "lacks"
                } else {
                    "would also match"
                }
            ));
        }
    }
    Ok(stage)
}

#[test]
fn every_test_runs_in_exactly_one_ci_stage() {
    let tests = all_tests();
    assert!(tests.len() > 100, "found only {} tests", tests.len());
    let mut errors = Vec::new();
    let mut counts = vec![
        (Stage::Tests, 0usize),
        (Stage::Gpu, 0),
        (Stage::RealData, 0),
        (Stage::KnownGap, 0),
        (Stage::Manual, 0),
    ];
    for t in &tests {
        match stage(t) {
            Ok(s) => {
                if let Some(c) = counts.iter_mut().find(|(k, _)| *k == s) {
                    c.1 += 1;
                }
            }
            Err(e) => errors.push(format!("{}: {e}", t.place)),
        }
    }
    for f in source_files() {
        errors.extend(
            stray_gpu_helper_calls(&f)
                .into_iter()
                .map(|e| format!("{e}: GPU test helper called outside a gpu_ test")),
        );
    }
    println!("#[test] functions per CI stage: {counts:?}");
    assert!(errors.is_empty(), "misfiled tests:\n{}", errors.join("\n"));
    let gpu = counts.iter().find(|(s, _)| *s == Stage::Gpu).map(|c| c.1);
    assert!(gpu.unwrap_or(0) > 0, "no GPU tests found");
}

#[test]
fn ci_runs_the_gpu_and_real_data_stages_with_these_filters() {
    let ci = std::fs::read_to_string(Path::new(ROOT).join(".ci/run")).expect(".ci/run");
    for f in CI_FILTERS {
        assert!(ci.contains(f), ".ci/run does not run `{f}`");
    }
    assert!(
        ci.contains("RGBID_REQUIRE_GPU=1"),
        ".ci/run must require the GPU"
    );
}

#[test]
fn misfiled_tests_are_caught() {
    let t = |name: &str, ignore: Option<&str>, body: &str| TestFn {
        place: name.into(),
        lines: (0, 0),
        full_name: name.into(),
        name: name.into(),
        ignore: ignore.map(String::from),
        body: body.into(),
    };
    let gpu_body = "let Some(g) = rgbid::gpu::test_gpu(\"x\") else { return };";
    assert_eq!(
        stage(&t("gpu_x", Some(GPU_REASON), gpu_body)),
        Ok(Stage::Gpu)
    );
    assert_eq!(
        stage(&t("real_data_x", Some("needs ../shared/data"), "")),
        Ok(Stage::RealData)
    );
    assert_eq!(stage(&t("plain", None, "")), Ok(Stage::Tests));
    // A GPU test that is not ignored, or not named gpu_.
    assert!(stage(&t("gpu_x", None, gpu_body)).is_err());
    assert!(stage(&t("x", Some(GPU_REASON), gpu_body)).is_err());
    // An ignored test with no stage, and a real-data test the GPU filter would also pick up.
    assert!(stage(&t("x", Some("slow"), "")).is_err());
    assert!(stage(&t("data_on_gpu_x", Some("needs ../shared/data"), "")).is_err());
    // A known gap the GPU filter would run.
    assert!(stage(&t("known_gap_gpu_x", Some("known gap: y"), "")).is_err());
    assert!(calls_gpu_helper("rgbid::gpu::test_gpu(\"x\")") && calls_gpu_helper("test_gpu(x)"));
    assert!(!calls_gpu_helper("fn no_test_gpu(test: &str)"));
    assert!(stage(&t("gpu_x", Some(GPU_REASON), "rgbid::gpu::any_gpu()")).is_err());
}
