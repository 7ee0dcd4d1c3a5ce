//! Configuration as data on the command line: `rgbid config dump` round trips, `--config` and
//! `--set` layering on `rgbid slam` (recorded in summary.json), errors that name a mistyped
//! key, today's JSON odometry configuration files, and the provenance sidecar of
//! `rgbid odometry --out`.

use std::path::Path;

use rgbid::mono::MonoConfig;
use rgbid::odometry::{Estimator, GeometricParam, OdometryConfig};
use rgbid::place::LoopDetectorParams;
use rgbid::scale::{DynScaleConfig, UpAxis};
use rgbid::segment::SegmentConfig;
use rgbid::slam::SlamConfig;
use serde::de::DeserializeOwned;

#[path = "common/cli.rs"]
mod cli;
use cli::{rgbid, text};

fn dump<T: DeserializeOwned>(command: &str) -> T {
    let o = rgbid(&["config", "dump", "--command", command]);
    assert!(o.status.success(), "{}", text(&o));
    let toml_text = String::from_utf8(o.stdout).expect("utf-8");
    toml::from_str(&toml_text).unwrap_or_else(|e| panic!("{command}: {e}\n{toml_text}"))
}

#[test]
fn config_dump_parses_back_to_the_defaults() {
    assert_eq!(
        dump::<SlamConfig>("slam").odometry,
        OdometryConfig::default()
    );
    let slam: SlamConfig = dump("slam");
    assert!(slam.keyframe_colour, "keyframes keep colour by default");
    let o = rgbid(&["config", "dump", "--command", "slam"]);
    assert!(
        String::from_utf8_lossy(&o.stdout).contains("keyframe_colour = true"),
        "{}",
        text(&o)
    );
    // SlamConfig has no PartialEq (its parts do): compare the serialised forms.
    assert_eq!(
        serde_json::to_value(&slam).expect("json"),
        serde_json::to_value(SlamConfig::default()).expect("json")
    );
    assert_eq!(
        dump::<OdometryConfig>("odometry"),
        OdometryConfig::default()
    );
    assert_eq!(dump::<SegmentConfig>("segment"), SegmentConfig::default());
    assert_eq!(
        dump::<LoopDetectorParams>("place"),
        LoopDetectorParams::default()
    );
    assert_eq!(dump::<MonoConfig>("mono"), MonoConfig::default());
    // `rgbid scale` finds the up axis by default (a monocular world frame is arbitrary); the
    // library's default keeps -y, which the experiment harnesses' generated walks use.
    assert_eq!(
        dump::<DynScaleConfig>("scale"),
        DynScaleConfig {
            up: UpAxis::Auto,
            ..DynScaleConfig::default()
        }
    );
    // JSON too.
    let o = rgbid(&["config", "dump", "--command", "odometry", "--json"]);
    assert!(o.status.success(), "{}", text(&o));
    let back: OdometryConfig = serde_json::from_slice(&o.stdout).expect("json");
    assert_eq!(back, OdometryConfig::default());
}

#[test]
fn slam_takes_config_file_flags_and_set_in_that_order() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let cfg = tmp.path().join("c.toml");
    std::fs::write(
        &cfg,
        "keyframe_covisibility = 0.6\nlost_max_speed = 5.0\n\n[odometry]\nestimator = \"tukey\"\nlevels = 3\n",
    )
    .expect("write");
    let out = tmp.path().join("run");
    let o = rgbid(&[
        "slam",
        "--synth",
        "office:loop",
        "--frames",
        "8",
        "--width",
        "160",
        "--backend",
        "cpu",
        "--no-model",
        "--config",
        cfg.to_str().expect("path"),
        // A flag beats the file ...
        "--keyframe-covisibility",
        "0.65",
        "--estimator",
        "least-squares",
        // ... and --set beats both.
        "--set",
        "odometry.estimator=huber",
        "--out",
        out.to_str().expect("path"),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).expect("summary"))
            .expect("json");
    let p = &summary["provenance"];
    let c = &p["config"];
    assert_eq!(c["odometry"]["estimator"], "huber", "{p}");
    assert_eq!(c["odometry"]["levels"], 3, "{p}");
    assert_eq!(c["keyframe_covisibility"], 0.65, "{p}");
    assert_eq!(c["lost_max_speed"], 5.0, "{p}");
    assert_eq!(c["odometry"]["max_width"], 320, "{p}");
    assert_eq!(p["backend"], "cpu");
    assert_eq!(p["rgbid_version"], env!("CARGO_PKG_VERSION"));
    assert!(p["git_commit"].is_string() || p["git_commit"].is_null());
    let line: Vec<&str> = p["command_line"]
        .as_array()
        .expect("command line")
        .iter()
        .filter_map(|v| v.as_str())
        .collect();
    assert!(line.contains(&"odometry.estimator=huber"), "{line:?}");
    // The recorded configuration is itself a valid configuration.
    let back: SlamConfig = serde_json::from_value(c.clone()).expect("config");
    assert_eq!(back.odometry.estimator, Estimator::Huber);
}

#[test]
fn a_mistyped_key_is_an_error_that_names_it() {
    let o = rgbid(&[
        "slam",
        "--synth",
        "office:loop",
        "--set",
        "odometry.estimatr=huber",
    ]);
    assert!(!o.status.success());
    let t = text(&o);
    assert!(t.contains("unknown key `odometry.estimatr`"), "{t}");

    let tmp = tempfile::tempdir().expect("tempdir");
    let cfg = tmp.path().join("typo.toml");
    std::fs::write(&cfg, "[detector.query]\nmin_separatoin = 4\n").expect("write");
    let o = rgbid(&["config", "dump", "--config", cfg.to_str().expect("path")]);
    assert!(!o.status.success());
    let t = text(&o);
    assert!(
        t.contains("typo.toml") && t.contains("detector.query.min_separatoin"),
        "{t}"
    );

    // A value of the wrong type names its key as well.
    let o = rgbid(&["config", "dump", "--set", "odometry.levels=many"]);
    assert!(!o.status.success());
    let t = text(&o);
    assert!(t.contains("odometry.levels"), "{t}");
}

/// A small TUM folder rendered by `rgbid synth`.
fn tum_folder(dir: &Path) {
    let o = rgbid(&[
        "synth",
        "--frames",
        "6",
        "--width",
        "160",
        "--backend",
        "cpu",
        "--out",
        dir.to_str().expect("path"),
    ]);
    assert!(o.status.success(), "{}", text(&o));
}

#[test]
fn json_odometry_configs_still_load_and_outputs_get_a_sidecar() {
    let tmp = tempfile::tempdir().expect("tempdir");
    // A configuration file as written before TOML: JSON, partial, `null` for frame-to-frame.
    let json = tmp.path().join("depth.json");
    std::fs::write(
        &json,
        r#"{"geometric": "depth", "fixed_sigma_geo": 0.01, "reference_switch": null}"#,
    )
    .expect("write");
    let c = OdometryConfig::from_json_file(&json).expect("from_json_file");
    assert_eq!(c.geometric, GeometricParam::Depth);
    assert_eq!(c.reference_switch, None);
    let o = rgbid(&[
        "config",
        "dump",
        "--command",
        "odometry",
        "--json",
        "--config",
        json.to_str().expect("path"),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let back: OdometryConfig = serde_json::from_slice(&o.stdout).expect("json");
    assert_eq!(back, c);

    let seq = tmp.path().join("seq");
    tum_folder(&seq);
    let out = tmp.path().join("t.txt");
    let o = rgbid(&[
        "odometry",
        seq.to_str().expect("path"),
        "--config",
        json.to_str().expect("path"),
        "--set",
        "max_width=0",
        "--backend",
        "cpu",
        "--out",
        out.to_str().expect("path"),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let sidecar: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(tmp.path().join("t.txt.json")).expect("sidecar"),
    )
    .expect("json");
    assert_eq!(sidecar["config"]["geometric"], "depth", "{sidecar}");
    assert_eq!(sidecar["config"]["max_width"], 0, "{sidecar}");
    assert!(sidecar["config"]["reference_switch"].is_null(), "{sidecar}");
    assert_eq!(sidecar["backend"], "cpu");
}
