//! `rgbid scale`: true metric scale of a walking person's monocular trajectory (thesis ch. 3).

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use rgbid::experiments::scale::{
    estimate_sequence, evaluate_run, extra_sequences, load_run, median, percentile, run_cache_name,
    save_run, standard_sequences, Estimator, ExperimentConfig, MonoEstimator, RunReport,
    SequenceSpec, WindowTruth, METHODS,
};
use rgbid::gpu::ComputeBackend;
use rgbid::io::trajectory::{read_tum, write_tum};
use rgbid::scale::{
    arc_length_error, calibrate, CalibrationSample, DynScale, DynScaleConfig, DynScaleResult,
    UpAxis, GRIEVE_ALPHA, GRIEVE_BETA,
};

use super::options::{write_sidecar, ConfigArgs};
use super::plot::{write_png, Panel, Series, BLUE, RED};

/// `rgbid scale TRAJ ...` scales a trajectory; `calibrate` and `experiment` are subcommands.
#[derive(clap::Args)]
#[command(args_conflicts_with_subcommands = true)]
pub struct Args {
    #[command(subcommand)]
    command: Option<Command>,
    #[command(flatten)]
    run: RunArgs,
}

/// Subcommands of `rgbid scale`.
#[derive(clap::Subcommand)]
pub enum Command {
    /// Fit alpha, beta of V = alpha f^beta H to walks of known length (power fit). The file
    /// has one walk per line: `step_period_s distance_m time_s` (spaces or commas, # comments).
    Calibrate {
        /// Calibration file.
        file: PathBuf,
        /// Height of the walker, metres (> 0).
        #[arg(long, value_parser = crate::cli::options::range::positive)]
        height: f64,
    },
    /// Generated walking sequences (head, chest, stops, stairs; several seeds) with emulated
    /// monocular drift: tables of unscaled / optimSim3 / dynScale / dynScale+optimSim3, step
    /// frequency error, stop detection and alpha/beta sensitivity.
    Experiment(ExperimentArgs),
}

/// Options of scaling one trajectory.
#[derive(clap::Args)]
pub struct RunArgs {
    /// Unscaled TUM trajectory (`world_from_camera`, any units).
    traj: Option<PathBuf>,
    /// Rate the trajectory is resampled at, frames per second (`fps`); > 0 [default: 30].
    #[arg(long, value_parser = crate::cli::options::range::positive)]
    fps: Option<f64>,
    /// Height of the walker, metres (`model.height`; required unless the configuration
    /// file or --set gives it) (> 0).
    #[arg(long, value_parser = crate::cli::options::range::positive)]
    height: Option<f64>,
    /// alpha of V = alpha f^beta H (`model.alpha`); > 0 [default: Grieve's].
    #[arg(long, value_parser = crate::cli::options::range::positive)]
    alpha: Option<f64>,
    /// beta of V = alpha f^beta H (`model.beta`); any finite number [default: Grieve's].
    #[arg(long, value_parser = crate::cli::options::range::finite)]
    beta: Option<f64>,
    /// Up axis in the trajectory's world frame: x, y, z (signed), auto (normal of the
    /// positions' best-fit plane; a monocular world frame is arbitrary) or a,b,c (`up`)
    /// [default: auto].
    #[arg(long, allow_hyphen_values = true)]
    up: Option<String>,
    /// Analysis window t_DFT, seconds, >= 1 (`window`) [default: 4].
    #[arg(long, value_parser = crate::cli::options::range::at_least_one_real)]
    window: Option<f64>,
    /// Update period t_upd (section length), seconds, in (0, window] (`update`)
    /// [default: 1].
    #[arg(long, value_parser = crate::cli::options::range::positive)]
    update: Option<f64>,
    /// Number of particles, >= 10 (`filter.particles`) [default: 5000].
    #[arg(long, value_parser = crate::cli::options::range::at_least_ten)]
    particles: Option<usize>,
    /// Scale drift of the filter, decades per sqrt(s) (`filter.sigma_drift`); >= 0 [default: 0.1].
    #[arg(long, value_parser = crate::cli::options::range::non_negative)]
    sigma_drift: Option<f64>,
    /// Seed of the particle filter (`seed`) (any whole number, 0 to 2^64-1).
    #[arg(long, value_parser = crate::cli::options::range::seed)]
    seed: Option<u64>,
    /// Configuration: a `DynScaleConfig` file (`rgbid config dump --command scale`).
    #[command(flatten)]
    config: ConfigArgs,
    /// Output: the scaled TUM trajectory (metres).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Output: a PNG with step frequency, scale and walking speed per section against time.
    #[arg(long)]
    plot: Option<PathBuf>,
    /// Output: the sections as JSON.
    #[arg(long)]
    json: Option<PathBuf>,
    /// Ground truth (TUM, metres) for the arc-length error of the input and the result.
    #[arg(long)]
    gt: Option<PathBuf>,
}

/// Options of `rgbid scale experiment`.
#[derive(clap::Args)]
pub struct ExperimentArgs {
    /// Duration of each sequence, seconds (> 0).
    #[arg(long, value_parser = crate::cli::options::range::positive, default_value_t = 90.0)]
    duration: f64,
    /// Number of seeds per sequence (1 to 1000).
    #[arg(long, value_parser = crate::cli::options::range::seeds, default_value_t = 3)]
    seeds: u64,
    /// Number of particles (>= 10).
    #[arg(long, value_parser = crate::cli::options::range::at_least_ten, default_value_t = 5000)]
    particles: usize,
    /// Scale drift of the emulated monocular SLAM, std of ln s per sqrt(s) (>= 0).
    #[arg(long, value_parser = crate::cli::options::range::non_negative, default_value_t = 0.04)]
    drift: f64,
    /// Source of the monocular trajectories: `emulated` (ground truth with emulated scale
    /// drift, seconds) or `mono` (the monocular EKF on catadioptric images rendered along
    /// each walk: its own drift; ~70 ms of rendering per 400x400 frame).
    #[arg(long, default_value = "emulated", value_parser = ["emulated", "mono"])]
    estimator: String,
    /// Image side of the catadioptric camera with `--estimator mono`, pixels (16 to 16384 pixels).
    #[arg(long, value_parser = crate::cli::options::range::image_side, default_value_t = 400)]
    size: u32,
    /// Sequences to run, comma separated (head, chest, stops, stairs, flights); default the
    /// first four. `flights`: 60 risers at 2.0 steps/s with unequal legs (a stride-frequency
    /// oscillation stronger than the step's).
    #[arg(long, value_delimiter = ',')]
    sequences: Vec<String>,
    /// Stride-aware peak choice (`spectrum.stride_ratio`): a peak at twice the chosen one's
    /// frequency with at least this share of its density is taken for the step and the
    /// chosen one for the stride; 0 turns it off (0 to 1).
    #[arg(long, value_parser = crate::cli::options::range::unit, default_value_t = 0.4)]
    stride_ratio: f64,
    /// Folder for plots and TUM files (estimate, ground truth) of the first seed of every
    /// sequence.
    #[arg(long)]
    out_dir: Option<PathBuf>,
    /// Folder caching the monocular EKF runs (`--estimator mono`): a run found there (same
    /// sequence, seed, duration, image size) is read instead of rendered and filtered again;
    /// a missing one is computed and written. Lets the analysis be re-run in seconds.
    #[arg(long)]
    cache: Option<PathBuf>,
    /// CSV file with one row per analysis window of every run: true and estimated step
    /// frequency, spectral concentration, amplitude, walking / steady / consistent flags,
    /// estimated and true scale (for residual plots of the frequency and stop detection).
    #[arg(long)]
    windows: Option<PathBuf>,
    /// Also the thesis' table 3.1 sweep: dynScale's arc-length error (rigid alignment, % of
    /// the path) and per-section scale error for analysis windows t_DFT in {2, 3, 4, 6, 8} s
    /// and update periods t_upd in {0.5, 1, 2} s, on the same runs.
    #[arg(long)]
    sweep: bool,
    /// Output: the sweep as a JSON report (for docs/results via scripts/results.py).
    #[arg(long, requires = "sweep")]
    json: Option<PathBuf>,
}

/// One cell of the t_DFT / t_upd sweep.
#[derive(serde::Serialize)]
struct SweepRow {
    /// Analysis window t_DFT, seconds.
    t_dft: f64,
    /// Update period t_upd, seconds.
    t_upd: f64,
    /// Runs evaluated (sequences x seeds).
    runs: usize,
    /// Mean dynScale arc-length error over the runs, % of the path.
    rel_error_pct: f64,
    /// Largest dynScale arc-length error of a run, % of the path.
    rel_error_max_pct: f64,
    /// Median |s / s_true - 1| over the updated walking sections, %.
    scale_error_median_pct: f64,
    /// Share of the sections detected as walking, %.
    walking_pct: f64,
}

/// The sweep of the thesis' table 3.1 over the runs already estimated.
fn sweep(
    seqs: &[SequenceSpec],
    runs: &[(String, u64, rgbid::scale::EmulatedRun)],
    cfg: &ExperimentConfig,
    bar: &ProgressBar,
) -> Result<Vec<SweepRow>> {
    let mut rows = Vec::new();
    for t_dft in [2.0, 3.0, 4.0, 6.0, 8.0] {
        for t_upd in [0.5, 1.0, 2.0] {
            bar.set_message(format!("sweep t_DFT {t_dft} s, t_upd {t_upd} s"));
            let mut c = cfg.clone();
            c.dynscale.window = t_dft;
            c.dynscale.update = t_upd;
            let (mut rel, mut scale_err, mut walking, mut sections) =
                (Vec::new(), Vec::new(), 0, 0);
            for (name, seed, run) in runs {
                let Some(spec) = seqs.iter().find(|s| &s.name == name) else {
                    continue;
                };
                let r = evaluate_run(spec, *seed, run.clone(), &c)
                    .with_context(|| format!("sweep {name} seed {seed}, t_DFT {t_dft} s"))?;
                rel.push(100.0 * r.metric[2].relative);
                scale_err.extend(r.scale_errors.iter().map(|e| 100.0 * e));
                walking += r.dynscale.sections.iter().filter(|s| s.walking).count();
                sections += r.dynscale.sections.len();
                bar.inc(1);
            }
            rows.push(SweepRow {
                t_dft,
                t_upd,
                runs: rel.len(),
                rel_error_pct: rel.iter().sum::<f64>() / rel.len().max(1) as f64,
                rel_error_max_pct: rel.iter().cloned().fold(0.0, f64::max),
                scale_error_median_pct: median(&scale_err),
                walking_pct: 100.0 * walking as f64 / sections.max(1) as f64,
            });
        }
    }
    Ok(rows)
}

/// Runs `rgbid scale`.
pub fn run(a: Args) -> Result<()> {
    match a.command {
        Some(Command::Calibrate { file, height }) => run_calibrate(&file, height),
        Some(Command::Experiment(e)) => run_experiment(&e),
        None => run_scale(&a.run),
    }
}

fn run_calibrate(file: &Path, height: f64) -> Result<()> {
    let text =
        std::fs::read_to_string(file).with_context(|| format!("reading {}", file.display()))?;
    let mut samples = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let s = line.trim();
        if s.is_empty() || s.starts_with('#') {
            continue;
        }
        let v: Vec<f64> = s
            .split(|c: char| c.is_whitespace() || c == ',')
            .filter(|x| !x.is_empty())
            .map(|x| x.parse::<f64>())
            .collect::<Result<_, _>>()
            .with_context(|| format!("{}:{}: expected numbers", file.display(), i + 1))?;
        if v.len() != 3 {
            bail!(
                "{}:{}: expected step_period distance time, found {} values",
                file.display(),
                i + 1,
                v.len()
            );
        }
        samples.push(CalibrationSample {
            step_period: v[0],
            distance: v[1],
            time: v[2],
        });
    }
    let m = calibrate(height, &samples)?;
    println!(
        "alpha {:.4}  beta {:.4}  (height {:.2} m, {} walks)",
        m.alpha,
        m.beta,
        height,
        samples.len()
    );
    println!(
        "{:>10} {:>10} {:>12} {:>12} {:>8}",
        "f (Hz)", "V (m/s)", "model (m/s)", "Grieve (m/s)", "err %"
    );
    for s in &samples {
        let f = 1.0 / s.step_period;
        let v = s.distance / s.time;
        let g = GRIEVE_ALPHA * f.powf(GRIEVE_BETA) * height;
        println!(
            "{:10.3} {:10.3} {:12.3} {:12.3} {:8.2}",
            f,
            v,
            m.speed(f),
            g,
            100.0 * (m.speed(f) / v - 1.0)
        );
    }
    Ok(())
}

/// An `(x, y)` plot point.
type Point = (f64, f64);

/// Frequency, scale and speed per section against time, stacked; with `truth` (true step
/// frequency and true scale over time) drawn beside the estimates.
fn section_plot(
    path: &Path,
    r: &DynScaleResult,
    truth: Option<(&[Point], &[Point])>,
) -> Result<()> {
    let mid = |s: &rgbid::scale::Section| 0.5 * (s.t_start + s.t_end);
    let series = |label: &str, points: Vec<Point>, color, dots| Series {
        label: label.into(),
        points,
        color,
        dots,
    };
    // Sections that are not walking carry no frequency: a gap, not a zero.
    let freq: Vec<Point> = r
        .sections
        .iter()
        .map(|s| {
            let f = if s.walking {
                s.analysis.frequency
            } else {
                f64::NAN
            };
            (mid(s), f)
        })
        .collect();
    let scale: Vec<Point> = r.sections.iter().map(|s| (mid(s), s.scale)).collect();
    let speed: Vec<Point> = r.sections.iter().map(|s| (mid(s), s.speed())).collect();
    let mut f_series = vec![series("estimate (walking sections)", freq, BLUE, true)];
    let mut s_series = vec![series("estimate", scale, BLUE, false)];
    if let Some((f, s)) = truth {
        f_series.insert(0, series("ground truth", f.to_vec(), RED, false));
        s_series.insert(0, series("ground truth", s.to_vec(), RED, false));
    }
    let panel = |title: &str, y_label: &str, series| Panel {
        title: title.into(),
        x_label: "time (s)".into(),
        y_label: y_label.into(),
        series,
        equal_axes: false,
    };
    let panels = [
        panel("step frequency per section", "frequency (Hz)", f_series),
        panel("scale per section", "scale (m per SLAM unit)", s_series),
        panel(
            "walking speed per section",
            "speed (m/s)",
            vec![series("estimate", speed, BLUE, false)],
        ),
    ];
    write_png(path, &panels, (3, 1), (1200, 1200))
}

/// The defaults of `rgbid scale TRAJ`: [`DynScaleConfig::default`] with the up axis found from
/// the trajectory (a monocular SLAM's world frame is arbitrary).
pub(crate) fn defaults() -> DynScaleConfig {
    DynScaleConfig {
        up: UpAxis::Auto,
        ..DynScaleConfig::default()
    }
}

fn run_scale(a: &RunArgs) -> Result<()> {
    let Some(path) = &a.traj else {
        bail!("give a trajectory: rgbid scale TRAJ --height H [--out scaled.txt] (or a subcommand: calibrate, experiment)");
    };
    let height_given = a.height.is_some()
        || a.config.config.is_some()
        || a.config
            .set
            .iter()
            .any(|s| s.path.join(".") == "model.height");
    if !height_given {
        bail!("--height (metres) is required to scale a trajectory");
    }
    let traj = read_tum(path)?;
    let cfg = a.config.resolve(defaults(), |c| {
        if let Some(v) = a.height {
            c.model.height = v;
        }
        if let Some(v) = a.fps {
            c.fps = v;
        }
        if let Some(v) = a.alpha {
            c.model.alpha = v;
        }
        if let Some(v) = a.beta {
            c.model.beta = v;
        }
        if let Some(up) = &a.up {
            c.up = UpAxis::parse(up)?;
        }
        if let Some(v) = a.window {
            c.window = v;
        }
        if let Some(v) = a.update {
            c.update = v;
        }
        if let Some(v) = a.particles {
            c.filter.particles = v;
        }
        if let Some(v) = a.sigma_drift {
            c.filter.sigma_drift = v;
        }
        if let Some(v) = a.seed {
            c.seed = v;
        }
        Ok(())
    })?;
    let r = DynScale::new(cfg.clone())?.run(&traj)?;
    let u = r.up;
    println!(
        "{} poses over {:.1} s, up [{:.3} {:.3} {:.3}], {} sections",
        traj.len(),
        traj[traj.len() - 1].timestamp - traj[0].timestamp,
        u[0],
        u[1],
        u[2],
        r.sections.len()
    );
    println!(
        "{:>8} {:>8} {:>5} {:>8} {:>10} {:>8} {:>9} {:>9} {:>8}",
        "t0 (s)", "t1 (s)", "walk", "f (Hz)", "power", "conc", "scale", "V (m/s)", "used"
    );
    for s in &r.sections {
        println!(
            "{:8.2} {:8.2} {:>5} {:8.3} {:10.3e} {:8.2} {:9.4} {:9.3} {:>8}",
            s.t_start,
            s.t_end,
            if s.walking { "yes" } else { "no" },
            s.analysis.frequency,
            s.analysis.peak_power,
            s.analysis.concentration,
            s.scale,
            s.speed(),
            if s.consistent { "yes" } else { "no" }
        );
    }
    let walking = r.sections.iter().filter(|s| s.walking).count();
    println!(
        "walking in {walking}/{} sections; final scale {:.4} m/unit",
        r.sections.len(),
        r.sections[r.sections.len() - 1].scale
    );
    if let Some(gt_path) = &a.gt {
        let gt = read_tum(gt_path)?;
        for (name, est) in [("input", &traj), ("scaled", &r.scaled)] {
            let e = arc_length_error(&gt, est, 1000, false)?;
            println!(
                "{name:>7}: arc-length error mean {:.3} m, max {:.3} m, relative {:.2} % of {:.1} m",
                e.mean,
                e.max,
                100.0 * e.relative,
                e.gt_length
            );
        }
    }
    if let Some(out) = &a.out {
        write_tum(out, &r.scaled)?;
        write_sidecar(out, &cfg, &ComputeBackend::Cpu)?;
        println!("wrote {}", out.display());
    }
    if let Some(p) = &a.json {
        let sections = serde_json::to_string_pretty(&r.sections)?;
        std::fs::write(p, sections).with_context(|| format!("writing {}", p.display()))?;
        println!("wrote {}", p.display());
    }
    if let Some(p) = &a.plot {
        section_plot(p, &r, None)?;
        println!(
            "wrote {} (panels: step frequency Hz, scale m/unit, speed m/s vs time)",
            p.display()
        );
    }
    super::outcome::warnings(walking_warning(walking, r.sections.len(), r.up))
}

/// A warning when fewer than half of the `sections` were detected as walking: the scale
/// rests on few measurements, and a wrong up axis (`up`, world frame) is the usual cause.
pub(crate) fn walking_warning(walking: usize, sections: usize, up: [f64; 3]) -> Vec<String> {
    if 2 * walking >= sections {
        return Vec::new();
    }
    vec![format!(
        "only {walking} of {sections} sections were detected as walking (up axis [{:.3} {:.3} {:.3}]): \
         the scale rests on few windows; check --up and --height",
        up[0], up[1], up[2]
    )]
}

fn stats_line(label: &str, v: &[f64]) -> String {
    format!(
        "{label:<8} n {:4}  mean {:.4}  p95 {:.4}  max {:.4}  within 0.05 Hz {:5.1} %",
        v.len(),
        v.iter().sum::<f64>() / v.len().max(1) as f64,
        percentile(v, 0.95),
        v.iter().cloned().fold(0.0, f64::max),
        100.0 * v.iter().filter(|e| **e < 0.05).count() as f64 / v.len().max(1) as f64
    )
}

/// Writes the per-window CSV of `rgbid scale experiment --windows`.
fn write_windows(
    path: &Path,
    seqs: &[SequenceSpec],
    reports: &[RunReport],
    fps: f64,
) -> Result<()> {
    use std::fmt::Write as _;
    let mut out = String::from(
        "sequence,seed,window_start,t_end,f_true_mean,f_true_min,f_true_max,f_est,frequency_span,concentration,amplitude,walking,steady,consistent,scale,true_scale\n",
    );
    for r in reports {
        let Some(spec) = seqs.iter().find(|s| s.name == r.sequence) else {
            continue;
        };
        let t0 = r.run.est.first().map_or(0.0, |p| p.timestamp);
        for s in &r.dynscale.sections {
            let truth = WindowTruth::of(&spec.params, s.window_start, s.t_end, fps);
            let i = (((s.t_end - t0) * fps).round().max(0.0) as usize)
                .min(r.run.true_scale.len().saturating_sub(1));
            let true_scale = r.run.true_scale.get(i).copied().unwrap_or(f64::NAN);
            let _ = writeln!(
                out,
                "{},{},{:.3},{:.3},{:.4},{:.4},{:.4},{:.4},{:.1},{:.4},{:.6},{},{},{},{:.6},{:.6}",
                r.sequence,
                r.seed,
                s.window_start,
                s.t_end,
                truth.mean,
                truth.min,
                truth.max,
                s.analysis.frequency,
                s.frequency_span,
                s.analysis.concentration,
                s.analysis.amplitude,
                u8::from(s.walking),
                u8::from(s.steady),
                u8::from(s.consistent),
                s.scale,
                true_scale
            );
        }
    }
    std::fs::write(path, out).with_context(|| format!("writing {}", path.display()))
}

fn run_experiment(a: &ExperimentArgs) -> Result<()> {
    let mut seqs = standard_sequences(a.duration);
    if !a.sequences.is_empty() {
        seqs.extend(extra_sequences(a.duration));
        for name in &a.sequences {
            if !seqs.iter().any(|s| &s.name == name) {
                bail!("unknown sequence {name:?} (head, chest, stops, stairs, flights)");
            }
        }
        seqs.retain(|s| a.sequences.contains(&s.name));
    }
    let mut cfg = ExperimentConfig::default();
    cfg.dynscale.filter.particles = a.particles;
    cfg.dynscale.spectrum.stride_ratio = a.stride_ratio;
    cfg.drift.drift = a.drift;
    if a.estimator == "mono" {
        cfg.estimator = Estimator::Monocular(MonoEstimator {
            size: a.size,
            ..MonoEstimator::default()
        });
    }
    let alpha_factors = [0.8, 0.9, 1.1, 1.2];
    let beta_deltas = [-0.2, -0.1, 0.1, 0.2];
    let frames = (a.duration * cfg.fps).floor() as u64;
    let per_run = if a.estimator == "mono" { frames } else { 1 };
    let sens_seqs = seqs
        .iter()
        .filter(|s| s.name == "head" || s.name == "chest")
        .count() as u64;
    let total = seqs.len() as u64 * a.seeds * per_run
        + sens_seqs * (alpha_factors.len() + beta_deltas.len()) as u64 * a.seeds
        + if a.sweep {
            15 * seqs.len() as u64 * a.seeds
        } else {
            0
        };
    let bar = ProgressBar::new(total);
    bar.set_style(
        ProgressStyle::with_template(
            "{msg} {bar:30} {pos}/{len} [{elapsed_precise}<{eta_precise}]",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    for d in [&a.out_dir, &a.cache].into_iter().flatten() {
        std::fs::create_dir_all(d).with_context(|| format!("creating {}", d.display()))?;
    }
    let mut reports: Vec<RunReport> = Vec::new();
    let mut runs = Vec::new();
    for spec in &seqs {
        for seed in 0..a.seeds {
            bar.set_message(format!("{} seed {seed}", spec.name));
            let done = bar.position();
            let cached = match (&a.cache, run_cache_name(spec, seed, &cfg)) {
                (Some(d), Some(name)) => Some(d.join(name)),
                _ => None,
            };
            let run = match &cached {
                Some(p) if p.exists() => load_run(p)?,
                _ => {
                    let run = estimate_sequence(spec, seed, &cfg, &mut |i, _| {
                        if per_run > 1 {
                            bar.set_position(done + i as u64);
                        }
                    })
                    .with_context(|| format!("{} seed {seed}", spec.name))?;
                    if let Some(p) = &cached {
                        save_run(p, &run)?;
                    }
                    run
                }
            };
            bar.set_position(done + per_run);
            let r = evaluate_run(spec, seed, run.clone(), &cfg)
                .with_context(|| format!("{} seed {seed}", spec.name))?;
            runs.push((spec.name.clone(), seed, run));
            if let (Some(d), 0) = (&a.out_dir, seed) {
                let true_scale: Vec<(f64, f64)> = r
                    .run
                    .est
                    .iter()
                    .zip(&r.run.true_scale)
                    .step_by(10)
                    .map(|(p, s)| (p.timestamp, *s))
                    .collect();
                write_tum(&d.join(format!("{}_est.txt", spec.name)), &r.run.est)?;
                write_tum(&d.join(format!("{}_gt.txt", spec.name)), &r.run.gt)?;
                section_plot(
                    &d.join(format!("{}.png", spec.name)),
                    &r.dynscale,
                    Some((&r.true_frequency, &true_scale)),
                )?;
            }
            reports.push(r);
        }
    }
    if let Some(path) = &a.windows {
        write_windows(path, &seqs, &reports, cfg.fps)?;
    }
    // Sensitivity to alpha / beta errors on head and chest walks.
    let mut sens: Vec<(String, Vec<f64>, Vec<f64>)> = Vec::new();
    let variants: Vec<(String, f64, f64)> = alpha_factors
        .iter()
        .map(|f| (format!("alpha x{f:.1}"), *f, 0.0))
        .chain(
            beta_deltas
                .iter()
                .map(|d| (format!("beta {d:+.1}"), 1.0, *d)),
        )
        .collect();
    for (label, fa, db) in &variants {
        let (mut ratios, mut rel) = (Vec::new(), Vec::new());
        for spec in seqs
            .iter()
            .filter(|s| s.name == "head" || s.name == "chest")
        {
            for seed in 0..a.seeds {
                bar.set_message(format!("sensitivity {label}"));
                let mut c = cfg.clone();
                c.keep_model = true;
                c.dynscale.model.height = spec.params.height;
                c.dynscale.model.alpha = spec.params.alpha * fa;
                c.dynscale.model.beta = spec.params.beta + db;
                let Some((_, _, run)) = runs
                    .iter()
                    .find(|(name, s, _)| name == &spec.name && *s == seed)
                else {
                    continue;
                };
                let r = evaluate_run(spec, seed, run.clone(), &c)?;
                for s in r
                    .dynscale
                    .sections
                    .iter()
                    .filter(|s| s.walking && s.consistent)
                {
                    let i = (((s.t_end - r.run.est[0].timestamp) * c.fps).round() as usize)
                        .min(r.run.true_scale.len() - 1);
                    ratios.push(s.scale / r.run.true_scale[i]);
                }
                rel.push(r.metric[2].relative);
                bar.inc(1);
            }
        }
        sens.push((label.clone(), ratios, rel));
    }
    let sweep_rows = if a.sweep {
        Some(sweep(&seqs, &runs, &cfg, &bar)?)
    } else {
        None
    };
    bar.finish_and_clear();

    if a.estimator == "mono" {
        println!("Walking sequences: {} s each, {} seeds, 30 fps, monocular EKF on {}x{} catadioptric renders (its own scale drift; true local scale measured against ground truth over +-2 s; random global unit in [0.2, 5] m/unit on top), keyframes every 3 frames", a.duration, a.seeds, a.size, a.size);
    } else {
        println!("Walking sequences: {} s each, {} seeds, 30 fps, emulated monocular drift (ln-scale random walk {:.3}/sqrt(s), unknown global scale in [0.2, 5] m/unit), keyframes every 3 frames", a.duration, a.seeds, a.drift);
    }
    println!(
        "\nPosition error by normalised arc length, rigid alignment (metric), mean over seeds;"
    );
    println!(
        "shape rel: after a similarity alignment; len ratio: estimated / true path length (median)"
    );
    println!(
        "{:<8} {:<20} {:>10} {:>10} {:>10} {:>14} {:>10}",
        "seq", "method", "mean (m)", "max (m)", "rel (%)", "shape rel (%)", "len ratio"
    );
    for spec in &seqs {
        let rs: Vec<&RunReport> = reports.iter().filter(|r| r.sequence == spec.name).collect();
        let n = rs.len().max(1) as f64;
        for (k, m) in METHODS.iter().enumerate() {
            let avg = |f: &dyn Fn(&RunReport) -> f64| rs.iter().map(|r| f(r)).sum::<f64>() / n;
            println!(
                "{:<8} {:<20} {:10.3} {:10.3} {:10.2} {:14.2} {:10.3}",
                spec.name,
                m,
                avg(&|r| r.metric[k].mean),
                avg(&|r| r.metric[k].max),
                100.0 * avg(&|r| r.metric[k].relative),
                100.0 * avg(&|r| r.shape[k].relative),
                median(
                    &rs.iter()
                        .map(|r| r.metric[k].est_length / r.metric[k].gt_length)
                        .collect::<Vec<_>>()
                )
            );
        }
        let loops: usize = rs.iter().map(|r| r.loops).sum();
        let len = rs.iter().map(|r| r.metric[0].gt_length).sum::<f64>() / n;
        println!(
            "{:<8} ({} loop closures in all, path {:.0} m on average)",
            "", loops, len
        );
    }
    println!("\nStep frequency error in steady-walking windows (Hz)");
    for spec in &seqs {
        let v: Vec<f64> = reports
            .iter()
            .filter(|r| r.sequence == spec.name)
            .flat_map(|r| r.frequency_errors.clone())
            .collect();
        println!("{}", stats_line(&spec.name, &v));
    }
    let all: Vec<f64> = reports
        .iter()
        .flat_map(|r| r.frequency_errors.clone())
        .collect();
    println!("{}", stats_line("all", &all));
    println!("\nStop detection (windows >= 75 % standing detected as not walking; fully walking windows called standing)");
    for spec in &seqs {
        let rs = reports.iter().filter(|r| r.sequence == spec.name);
        let (mut s, mut w) = ((0, 0), (0, 0));
        for r in rs {
            s.0 += r.stop_windows.0;
            s.1 += r.stop_windows.1;
            w.0 += r.walk_windows.0;
            w.1 += r.walk_windows.1;
        }
        println!(
            "{:<8} stops detected {:3}/{:<3}  false stops {:3}/{:<3}",
            spec.name, s.1, s.0, w.1, w.0
        );
    }
    println!("\nScale error per updated walking section |s/s_true - 1| (%)");
    for spec in &seqs {
        let v: Vec<f64> = reports
            .iter()
            .filter(|r| r.sequence == spec.name)
            .flat_map(|r| r.scale_errors.clone())
            .collect();
        println!(
            "{:<8} n {:4}  median {:6.2}  p90 {:6.2}",
            spec.name,
            v.len(),
            100.0 * median(&v),
            100.0 * percentile(&v, 0.9)
        );
    }
    if let Some(rows) = &sweep_rows {
        println!("\nTable 3.1 sweep: dynScale arc-length error (rigid, % of the path; mean and max over runs), median per-section scale error, walking sections");
        println!(
            "{:>9} {:>9} {:>5} {:>10} {:>10} {:>14} {:>10}",
            "t_DFT (s)", "t_upd (s)", "runs", "rel (%)", "max (%)", "scale err (%)", "walking %"
        );
        for r in rows {
            println!(
                "{:9.1} {:9.1} {:5} {:10.2} {:10.2} {:14.2} {:10.1}",
                r.t_dft,
                r.t_upd,
                r.runs,
                r.rel_error_pct,
                r.rel_error_max_pct,
                r.scale_error_median_pct,
                r.walking_pct
            );
        }
        if let Some(path) = &a.json {
            let body = serde_json::json!({
                "estimator": a.estimator,
                "duration_s": a.duration,
                "seeds": a.seeds,
                "particles": a.particles,
                "drift": a.drift,
                "sequences": seqs.iter().map(|s| s.name.clone()).collect::<Vec<_>>(),
                "rows": rows,
            });
            super::report::write(path, "scale-sweep", &super::report::meta(Vec::new()), &body)?;
        }
    }
    println!("\nSensitivity to walking-model errors (head + chest): s/s_true per section, dynScale relative error");
    if sens.iter().all(|(_, ratios, _)| ratios.is_empty()) {
        println!("  (not run: it needs the head or chest sequence)");
        return Ok(());
    }
    let expected = |fa: f64, db: f64| fa * 1.6f64.powf(db);
    for ((label, ratios, rel), (_, fa, db)) in sens.iter().zip(&variants) {
        println!(
            "{:<11} median s/s_true {:.3} (alpha' f^beta' / alpha f^beta at 1.6 Hz: {:.3})  dynScale rel {:5.2} %",
            label,
            median(ratios),
            expected(*fa, *db),
            100.0 * rel.iter().sum::<f64>() / rel.len().max(1) as f64
        );
    }
    Ok(())
}
