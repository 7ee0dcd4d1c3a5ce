//! Trajectory formats on the command line: `rgbid odometry --out` writes TUM, KITTI and EuRoC
//! files of the same run, and `rgbid eval` reads each (detected) to the same figures.

use std::path::Path;

#[path = "common/cli.rs"]
mod cli;
use cli::{rgbid, text};

fn path(p: &Path) -> &str {
    p.to_str().expect("utf-8 path")
}

/// `rgbid eval --json` of `est` against `gt`: (ATE RMSE m, RPE translation RMSE m, matched).
fn eval(gt: &Path, est: &Path, extra: &[&str]) -> (f64, f64, u64) {
    let mut args = vec!["eval", path(gt), path(est), "--json"];
    args.extend_from_slice(extra);
    let o = rgbid(&args);
    assert!(o.status.success(), "{}", text(&o));
    let m: serde_json::Value = serde_json::from_slice(&o.stdout).expect("json");
    (
        m["ate"]["translation"]["rmse"].as_f64().expect("ate"),
        m["rpe_frame"]["translation_m"]["rmse"]
            .as_f64()
            .expect("rpe"),
        m["matched"].as_u64().expect("matched"),
    )
}

#[test]
fn odometry_writes_each_format_and_eval_reads_them_alike() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let seq = tmp.path().join("seq");
    let o = rgbid(&[
        "synth",
        "--frames",
        "8",
        "--width",
        "160",
        "--backend",
        "cpu",
        "--out",
        path(&seq),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let gt = seq.join("groundtruth.txt");
    let mut figures = Vec::new();
    for name in ["t.txt", "t.kitti", "t.csv"] {
        let out = tmp.path().join(name);
        let o = rgbid(&[
            "odometry",
            path(&seq),
            "--backend",
            "cpu",
            "--out",
            path(&out),
        ]);
        assert!(o.status.success(), "{name}: {}", text(&o));
        figures.push((name, eval(&gt, &out, &[])));
    }
    assert!(tmp.path().join("t.times.txt").is_file());
    assert!(std::fs::read_to_string(tmp.path().join("t.csv"))
        .expect("csv")
        .starts_with("#timestamp [ns]"));
    let (_, (ate, rpe, matched)) = figures[0];
    assert_eq!(matched, 8);
    assert!(ate < 0.02, "ATE {ate}");
    for (name, (a, r, m)) in &figures[1..] {
        assert_eq!(*m, matched, "{name}");
        assert!(
            (a - ate).abs() < 1e-5 && (r - rpe).abs() < 1e-5,
            "{name}: {a} {r} vs {ate} {rpe}"
        );
    }
    // A clock offset larger than the matching window leaves nothing to match.
    let o = rgbid(&[
        "eval",
        path(&gt),
        path(&tmp.path().join("t.csv")),
        "--t-offset",
        "-5",
    ]);
    assert!(!o.status.success());
}
