//! Formats on the command line: `rgbid odometry --out` writes TUM, KITTI and EuRoC files of the
//! same run, and `rgbid eval` reads each (detected) to the same figures and plots them;
//! `rgbid export` converts a run folder's or map's trajectory, model and pose graph.

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

/// Writes a TUM trajectory of `n` poses on a circle of radius 1 m in the x-z plane at 10 Hz,
/// with `offset` added to x.
fn circle(path: &Path, n: usize, offset: f64) {
    let lines: Vec<String> = (0..n)
        .map(|i| {
            let a = i as f64 / n as f64 * std::f64::consts::TAU;
            let x = a.cos() + offset * (i as f64 / n as f64);
            format!("{:.3} {x:.6} 0.1 {:.6} 0 0 0 1", 0.1 * i as f64, a.sin())
        })
        .collect();
    std::fs::write(path, lines.join("\n") + "\n").expect("write trajectory");
}

#[test]
fn eval_plots_top_view_and_error_over_time() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (gt, est, png) = (
        tmp.path().join("gt.txt"),
        tmp.path().join("est.txt"),
        tmp.path().join("plot.png"),
    );
    circle(&gt, 60, 0.0);
    circle(&est, 60, 0.2);
    let o = rgbid(&["eval", path(&gt), path(&est), "--plot", path(&png)]);
    assert!(o.status.success(), "{}", text(&o));
    let img = image::open(&png).expect("plot is a PNG").to_rgb8();
    assert_eq!(img.dimensions(), (1600, 700));
    let count = |c: [u8; 3]| img.pixels().filter(|p| p.0 == c).count();
    // Both trajectories and the error curve are drawn in their colours, and text is there.
    let (blue, dark) = (count([30, 80, 200]), count([40, 40, 40]));
    assert!(blue > 500 && dark > 300, "blue {blue} dark {dark}");
    let white = count([255, 255, 255]);
    assert!(white < 1600 * 700 * 98 / 100, "the plot is almost empty");

    // Without a font the error says how to get one, and no plot is written.
    let png2 = tmp.path().join("plot2.png");
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_rgbid"))
        .args(["eval", path(&gt), path(&est), "--plot", path(&png2)])
        .env("RGBID_FONT", tmp.path().join("no-such-font.ttf"))
        .output()
        .expect("running rgbid");
    assert!(!o.status.success());
    let t = text(&o);
    assert!(
        t.contains("no-such-font.ttf") && t.contains("RGBID_FONT"),
        "{t}"
    );
    assert!(!png2.exists());
}

#[test]
fn export_writes_trajectories_models_and_graphs_of_runs_and_maps() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let (run, map) = (tmp.path().join("run"), tmp.path().join("map.bin"));
    let o = rgbid(&[
        "slam",
        "--synth",
        "office:handheld",
        "--frames",
        "40",
        "--width",
        "160",
        "--backend",
        "cpu",
        "--out",
        path(&run),
        "--map-out",
        path(&map),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let export = |input: &Path, format: &str, out: &str, extra: &[&str]| {
        let out = tmp.path().join(out);
        let mut args = vec![
            "export",
            path(input),
            "--format",
            format,
            "--out",
            path(&out),
        ];
        args.extend_from_slice(extra);
        (rgbid(&args), out)
    };
    let traj = rgbid::io::trajectory::read_trajectory(&run.join("trajectory.txt")).expect("traj");
    let keyframes = rgbid::io::trajectory::read_tum(&run.join("keyframes.txt")).expect("kfs");
    assert!(keyframes.len() >= 2, "{} keyframes", keyframes.len());

    // Trajectories: the run's, converted, read back to the same poses.
    for (format, name) in [("tum", "t.txt"), ("kitti", "t.kitti"), ("euroc", "t.csv")] {
        let (o, out) = export(&run, format, name, &[]);
        assert!(o.status.success(), "{format}: {}", text(&o));
        let back = rgbid::io::trajectory::read_trajectory(&out).expect("read back");
        assert_eq!(back.len(), traj.len(), "{format}");
        for (a, b) in back.iter().zip(&traj) {
            assert!((a.timestamp - b.timestamp).abs() < 1e-6, "{format}");
            let d = a.world_from_camera.translation - b.world_from_camera.translation;
            assert!(d.length() < 1e-5, "{format}: {d}");
        }
    }
    // The map's keyframe poses are the run's keyframes.
    let (o, out) = export(&map, "tum", "kf.txt", &[]);
    assert!(o.status.success(), "{}", text(&o));
    let kf = rgbid::io::trajectory::read_tum(&out).expect("kf");
    assert_eq!(kf.len(), keyframes.len());
    let (o, out) = export(&run, "tum", "kf2.txt", &["--keyframes"]);
    assert!(o.status.success(), "{}", text(&o));
    assert_eq!(
        rgbid::io::trajectory::read_tum(&out).expect("kf2").len(),
        keyframes.len()
    );

    // Models: PLY from the run folder and rebuilt from the map agree; OBJ has one vertex line
    // per point.
    let (o, ply) = export(&run, "ply", "run.ply", &[]);
    assert!(o.status.success(), "{}", text(&o));
    let run_points = rgbid::io::ply::read_ply(&ply).expect("ply");
    assert!(run_points.len() > 1000, "{} points", run_points.len());
    // The generated frames have colour: the model is coloured, not grey.
    let model = rgbid::io::ply::read_ply(&run.join("model.ply")).expect("model");
    assert_eq!(model, run_points);
    let coloured = run_points
        .iter()
        .filter(|(_, c)| c[0] != c[1] || c[1] != c[2])
        .count();
    assert!(
        coloured > run_points.len() / 2,
        "{coloured} of {} points coloured",
        run_points.len()
    );
    let (o, ply) = export(&map, "ply", "map.ply", &[]);
    assert!(o.status.success(), "{}", text(&o));
    let map_points = rgbid::io::ply::read_ply(&ply).expect("ply");
    assert_eq!(map_points.len(), run_points.len());
    // The map keeps the keyframes' colour: the same colours as the run's model.
    for ((p, c), (q, k)) in map_points.iter().zip(&run_points) {
        assert!((*p - *q).length() < 1e-5, "{p} {q}");
        assert_eq!(c, k);
    }
    let (o, obj) = export(&map, "obj", "map.obj", &[]);
    assert!(o.status.success(), "{}", text(&o));
    let obj = std::fs::read_to_string(obj).expect("obj");
    let vertices: Vec<&str> = obj.lines().filter(|l| l.starts_with("v ")).collect();
    assert_eq!(vertices.len(), run_points.len());
    // OBJ colour in 0..1 per vertex, as the PLY's.
    for (line, (_, c)) in vertices.iter().zip(&map_points).take(100) {
        let rgb: Vec<f64> = line
            .split_whitespace()
            .skip(4)
            .map(|v| v.parse().expect("number"))
            .collect();
        for k in 0..3 {
            assert!(
                (rgb[k] * 255.0 - f64::from(c[k])).abs() < 0.02,
                "{line} {c:?}"
            );
        }
    }

    // The pose graph: one vertex per keyframe, the keyframe chain as edges, readable as g2o.
    let (o, g2o) = export(&map, "g2o", "map.g2o", &[]);
    assert!(o.status.success(), "{}", text(&o));
    let g = rgbid::graph::g2o::read_g2o(&g2o).expect("g2o");
    let rgbid::graph::g2o::LoadedGraph::Se3(g) = g.graph else {
        panic!("an SE(3) graph");
    };
    assert_eq!(g.poses.len(), keyframes.len());
    assert!(g.edges.len() >= keyframes.len() - 1);
    assert_eq!(g.fixed.iter().filter(|f| **f).count(), 1);

    // A run folder has no graph; a folder that is no run folder is named.
    let (o, _) = export(&run, "g2o", "run.g2o", &[]);
    assert!(
        !o.status.success() && text(&o).contains("--map-out"),
        "{}",
        text(&o)
    );
    let (o, _) = export(tmp.path(), "tum", "x.txt", &[]);
    assert!(
        !o.status.success() && text(&o).contains("not a run folder"),
        "{}",
        text(&o)
    );
}

/// `rgbid slam --live replay:FOLDER@FPS --record DIR` (a simulated camera) tracks what it
/// receives and records it; `rgbid slam DIR` on the recording gives the same trajectory when
/// no frame was dropped. A live source this build lacks is named with the feature to build.
#[test]
fn live_replay_records_and_the_recording_replays_to_the_same_trajectory() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let seq = tmp.path().join("seq");
    let o = rgbid(&[
        "synth",
        "--frames",
        "20",
        "--width",
        "160",
        "--backend",
        "cpu",
        "--out",
        path(&seq),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let (rec, live_out, replay_out) = (
        tmp.path().join("rec"),
        tmp.path().join("live"),
        tmp.path().join("replay"),
    );
    let live = format!("replay:{}@8", path(&seq));
    let o = rgbid(&[
        "slam",
        "--live",
        &live,
        "--record",
        path(&rec),
        "--backend",
        "cpu",
        "--out",
        path(&live_out),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(
        text(&o).contains("live: 20 frames received, 0 dropped")
            && text(&o).contains("20 recorded"),
        "{}",
        text(&o)
    );
    let o = rgbid(&[
        "slam",
        path(&rec),
        "--backend",
        "cpu",
        "--out",
        path(&replay_out),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let read =
        |dir: &Path| std::fs::read_to_string(dir.join("trajectory.txt")).expect("trajectory");
    let (a, b) = (read(&live_out), read(&replay_out));
    assert_eq!(a.lines().filter(|l| !l.starts_with('#')).count(), 20);
    assert_eq!(a, b, "live and replayed trajectories differ");
    // The replayed folder's ground truth came along for the live run's evaluation.
    assert!(live_out.join("groundtruth.txt").exists());

    let o = rgbid(&[
        "slam",
        "--live",
        "kinect",
        "--out",
        path(&tmp.path().join("x")),
    ]);
    assert_eq!(o.status.code(), Some(1), "{}", text(&o));
    assert!(text(&o).contains("`kinect`"), "{}", text(&o));
    if !cfg!(feature = "openni2") {
        let o = rgbid(&[
            "slam",
            "--live",
            "openni2",
            "--out",
            path(&tmp.path().join("y")),
        ]);
        assert!(text(&o).contains("--features openni2"), "{}", text(&o));
    }
}
