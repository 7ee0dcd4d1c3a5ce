//! Machine-readable benchmark reports (`--json FILE` on the benchmarks).
//!
//! Every report is one JSON object `{"meta": {...}, "benchmark": NAME, ...}`: `meta` says when,
//! from which commit, with which command and on which machine the figures were measured, and
//! the rest holds the rows the benchmark printed. `scripts/results.py` renders
//! `docs/results/*.json` into `docs/results.md`, so the published figures are never typed by
//! hand.

use std::path::Path;
use std::process::Command;

use anyhow::{Context, Result};
use serde::Serialize;

/// When, where and from what a benchmark ran.
#[derive(Debug, Clone, Serialize)]
pub struct Meta {
    /// UTC date-time the benchmark finished, RFC 3339 (`2026-12-02T09:15:00Z`).
    pub date_utc: String,
    /// `git rev-parse --short HEAD` of the source tree the binary was built from, or
    /// "unknown" when that tree is not a git checkout any more.
    pub commit: String,
    /// True when tracked files differed from that commit at run time (`None`: unknown).
    pub dirty: Option<bool>,
    /// Version of the rgbid crate.
    pub rgbid_version: String,
    /// The command line, arguments quoted where the shell would need it.
    pub command: String,
    /// The machine.
    pub machine: Machine,
    /// Load average over 1, 5 and 15 minutes when the report was written (/proc/loadavg): on
    /// a small machine other work skews the timings, less so the ratios of one run.
    pub load_average: Option<[f64; 3]>,
}

/// The machine a benchmark ran on.
#[derive(Debug, Clone, Serialize)]
pub struct Machine {
    /// CPU model (`model name` in /proc/cpuinfo), or "unknown".
    pub cpu: String,
    /// Logical cores this process may use.
    pub logical_cores: usize,
    /// Operating system (`PRETTY_NAME` of /etc/os-release and the kernel release on Linux).
    pub os: String,
    /// Names of the GPU adapters a GPU backend ran on in this benchmark (empty: none ran).
    pub gpu_adapters: Vec<String>,
}

/// Collects the metadata now; `gpu_adapters` lists the adapters a GPU backend ran on.
pub fn meta(gpu_adapters: Vec<String>) -> Meta {
    let (commit, dirty) = git_state();
    Meta {
        date_utc: utc_now(),
        commit,
        dirty,
        rgbid_version: env!("CARGO_PKG_VERSION").to_string(),
        command: command_line(),
        machine: Machine {
            cpu: cpu_model(),
            logical_cores: std::thread::available_parallelism().map_or(1, |n| n.get()),
            os: os_name(),
            gpu_adapters,
        },
        load_average: load_average(),
    }
}

/// Writes `{"meta": meta, "benchmark": name, ...body}` to `path` (pretty-printed), creating
/// its folder. `body` must serialise to a JSON object.
pub fn write(path: &Path, benchmark: &str, meta: &Meta, body: &impl Serialize) -> Result<()> {
    let mut doc = serde_json::Map::new();
    doc.insert("meta".into(), serde_json::to_value(meta)?);
    doc.insert("benchmark".into(), benchmark.into());
    match serde_json::to_value(body)? {
        serde_json::Value::Object(fields) => doc.extend(fields),
        other => {
            doc.insert("rows".into(), other);
        }
    }
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    let mut text = serde_json::to_string_pretty(&serde_json::Value::Object(doc))?;
    text.push('\n');
    std::fs::write(path, text).with_context(|| format!("writing {}", path.display()))?;
    println!("wrote {}", path.display());
    Ok(())
}

/// The version of a Python module as the given interpreter sees it (`MODULE.__version__`, else
/// the installed distribution of that name), if any.
pub fn python_module_version(python: &str, module: &str) -> Option<String> {
    let script = format!(
        "import importlib, importlib.metadata as md\n\
         m = importlib.import_module('{module}')\n\
         print(getattr(m, '__version__', None) or md.version('{module}'))"
    );
    let out = Command::new(python).arg("-c").arg(script).output().ok()?;
    let v = String::from_utf8_lossy(&out.stdout).trim().to_string();
    (out.status.success() && !v.is_empty()).then_some(v)
}

/// Commit and dirty flag of the tree the binary was built from (falling back to the current
/// directory when that tree is gone).
fn git_state() -> (String, Option<bool>) {
    let source = Path::new(env!("CARGO_MANIFEST_DIR"));
    let dir = if source.is_dir() {
        source.to_path_buf()
    } else {
        std::env::current_dir().unwrap_or_default()
    };
    let git = |args: &[&str]| {
        Command::new("git")
            .arg("-C")
            .arg(&dir)
            .args(args)
            .output()
            .ok()
            .filter(|o| o.status.success())
            .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string())
    };
    match git(&["rev-parse", "--short", "HEAD"]) {
        Some(commit) if !commit.is_empty() => {
            // Benchmark outputs are not source: a chain of benchmarks would otherwise mark
            // every run after the first as uncommitted.
            let dirty = git(&[
                "status",
                "--porcelain",
                "--untracked-files=no",
                "--",
                ".",
                ":(exclude)docs/results",
            ])
            .map(|s| !s.is_empty());
            (commit, dirty)
        }
        _ => ("unknown".into(), None),
    }
}

fn command_line() -> String {
    std::env::args()
        .map(|a| {
            let plain = !a.is_empty()
                && a.chars()
                    .all(|c| c.is_ascii_alphanumeric() || "-_./=:,+@%".contains(c));
            if plain {
                a
            } else {
                format!("'{}'", a.replace('\'', r"'\''"))
            }
        })
        .collect::<Vec<_>>()
        .join(" ")
}

fn cpu_model() -> String {
    std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split_once(':'))
                .map(|(_, v)| v.trim().to_string())
        })
        .unwrap_or_else(|| "unknown".into())
}

fn load_average() -> Option<[f64; 3]> {
    let s = std::fs::read_to_string("/proc/loadavg").ok()?;
    let mut v = s.split_whitespace().map(|x| x.parse::<f64>().ok());
    Some([v.next()??, v.next()??, v.next()??])
}

fn os_name() -> String {
    let pretty = std::fs::read_to_string("/etc/os-release")
        .ok()
        .and_then(|s| {
            s.lines()
                .find_map(|l| l.strip_prefix("PRETTY_NAME="))
                .map(|v| v.trim_matches('"').to_string())
        });
    let kernel = std::fs::read_to_string("/proc/sys/kernel/osrelease")
        .ok()
        .map(|s| s.trim().to_string());
    match (pretty, kernel) {
        (Some(p), Some(k)) => format!("{p}, Linux {k}"),
        (Some(p), None) => p,
        (None, Some(k)) => format!("Linux {k}"),
        (None, None) => format!("{} {}", std::env::consts::OS, std::env::consts::ARCH),
    }
}

/// Now in UTC as RFC 3339, to the second.
fn utc_now() -> String {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    utc_from_unix(secs)
}

/// RFC 3339 UTC date-time of a Unix time (days to civil date: H. Hinnant's algorithm).
fn utc_from_unix(secs: u64) -> String {
    let days = (secs / 86_400) as i64;
    let rem = secs % 86_400;
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    format!(
        "{year:04}-{month:02}-{day:02}T{:02}:{:02}:{:02}Z",
        rem / 3600,
        rem % 3600 / 60,
        rem % 60
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn utc_dates() {
        assert_eq!(utc_from_unix(0), "1970-01-01T00:00:00Z");
        assert_eq!(utc_from_unix(951_782_400), "2000-02-29T00:00:00Z");
        assert_eq!(utc_from_unix(1_700_000_000), "2023-11-14T22:13:20Z");
        assert_eq!(utc_from_unix(4_102_444_799), "2099-12-31T23:59:59Z");
    }

    #[test]
    fn report_has_meta_and_rows() {
        let dir = tempfile::tempdir().expect("temp dir");
        let path = dir.path().join("sub/r.json");
        let body = serde_json::json!({"rows": [{"method": "a", "ms": 1.5}]});
        write(&path, "test", &meta(vec![]), &body).expect("written");
        let v: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&path).expect("read")).expect("json");
        assert_eq!(v["benchmark"], "test");
        assert_eq!(v["rows"][0]["method"], "a");
        assert!(v["meta"]["date_utc"]
            .as_str()
            .is_some_and(|d| d.ends_with('Z')));
        assert!(v["meta"]["machine"]["logical_cores"]
            .as_u64()
            .is_some_and(|n| n >= 1));
    }
}
