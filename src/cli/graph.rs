//! `rgbid graph`: pose-graph optimisation, evaluation and benchmarks (thesis ch. 7).

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use rgbid::graph::curve::{CurveGraph2, CurveGraph3, CurveOptions};
use rgbid::graph::g2o::{read_g2o, write_g2o, G2oFile, LoadedGraph};
use rgbid::graph::isam::read_isam;
use rgbid::graph::{
    self, planar, Algorithm, EdgeCost, InitMethod, RobustKernel, SolveReport, SolverOptions,
    Termination,
};

/// Subcommands of `rgbid graph`.
#[derive(clap::Subcommand)]
pub enum Command {
    /// Optimise a pose graph (g2o or iSAM text) and write the result as g2o.
    Optimize(OptimizeArgs),
    /// Position RMSE (metres) of an estimated graph against a ground-truth graph, after a
    /// rigid alignment of the positions.
    Eval {
        /// Estimated graph (g2o or iSAM).
        est: PathBuf,
        /// Ground truth graph (g2o, or iSAM ground-truth edges composed along the tree).
        gt: PathBuf,
    },
    /// Run the optimiser over every pose-graph benchmark file and print a table (seconds,
    /// iterations, chi2, SE-Sync objective F against the published optimum f*).
    Bench(BenchArgs),
}

/// Parametrisation of the optimisation.
#[derive(Clone, Copy, Debug, clap::ValueEnum, PartialEq, Eq)]
pub enum Param {
    /// Full poses in SE(2) / SE(3).
    Se,
    /// Curve graph (thesis 7.4): positions only, in R^2 for 2D files and R^3 for 3D files,
    /// built from the initial poses; full poses are recovered afterwards.
    Curve,
    /// A nearly planar 3D graph projected onto its best-fit plane (thesis 7.4.6), optimised
    /// as a curve graph in R^2 and lifted back to 3D.
    Curve2d,
}

/// Cost of `--param se`.
#[derive(Clone, Copy, Debug, clap::ValueEnum, PartialEq, Eq)]
pub enum CostArg {
    /// Geodesic error whitened by the full information matrix (g2o / GTSAM; what chi2 is).
    Geodesic,
    /// The SE-Sync objective F (chordal rotation distance, isotropic weights).
    Sesync,
}

/// Initialisation choice.
#[derive(Clone, Copy, Debug, clap::ValueEnum, PartialEq, Eq)]
pub enum InitArg {
    /// Linear for 2D, chordal for 3D.
    Auto,
    /// The file's poses (spanning tree of the edges when it has none).
    Odometry,
    /// Linear 2D approximation.
    Linear,
    /// Chordal rotation relaxation (3D).
    Chordal,
}

/// Robust kernel choice.
#[derive(Clone, Copy, Debug, clap::ValueEnum, PartialEq, Eq)]
pub enum RobustArg {
    /// Plain least squares.
    None,
    /// Huber.
    Huber,
    /// Pseudo-Huber.
    PseudoHuber,
    /// Cauchy.
    Cauchy,
}

/// Algorithm choice.
#[derive(Clone, Copy, Debug, clap::ValueEnum, PartialEq, Eq)]
pub enum AlgoArg {
    /// Levenberg-Marquardt.
    Lm,
    /// Gauss-Newton.
    Gn,
}

/// Solver settings shared by `optimize` and `bench`.
#[derive(clap::Args, Clone)]
pub struct SolveArgs {
    /// Parametrisation.
    #[arg(long, value_enum, default_value = "se")]
    pub param: Param,
    /// Initialisation.
    #[arg(long, value_enum, default_value = "auto")]
    pub init: InitArg,
    /// Optimisation algorithm.
    #[arg(long, value_enum, default_value = "lm")]
    pub algorithm: AlgoArg,
    /// Robust kernel on every edge.
    #[arg(long, value_enum, default_value = "none")]
    pub robust: RobustArg,
    /// Kernel width (on the whitened residual norm), > 0.
    #[arg(long, value_parser = crate::cli::options::range::positive, default_value_t = 1.0)]
    pub robust_delta: f64,
    /// Maximum iterations (0: report the initialisation alone, e.g. the linear 2D
    /// approximation). Hard graphs need more than 100 (M3500c from the linear
    /// initialisation: 153) (a whole number >= 0).
    #[arg(long, value_parser = crate::cli::options::range::count, default_value_t = SolverOptions::default().max_iterations)]
    pub max_iterations: usize,
    /// Initial Levenberg-Marquardt damping, relative to the Hessian's diagonal. Default:
    /// 1e-9 after a linear / chordal initialisation (close to the optimum: nearly Gauss-Newton
    /// steps, 2-4x fewer iterations on the benchmark files), 1e-5 from odometry (safer far from
    /// it: 1e-9 ends in worse local minima on M3500b/c). Finite, > 0.
    #[arg(long, value_parser = crate::cli::options::range::positive)]
    pub initial_lambda: Option<f64>,
    /// Edge cost for `--param se`.
    #[arg(long, value_enum, default_value = "geodesic")]
    pub cost: CostArg,
    /// Curve-graph reduction: minimal distance (metres, >= 0) between kept nodes (0 keeps
    /// all).
    #[arg(long, value_parser = crate::cli::options::range::non_negative, default_value_t = 0.0)]
    pub th_d: f64,
    /// Curve-graph reduction: minimal rotation (radians, >= 0) between kept nodes.
    #[arg(long, value_parser = crate::cli::options::range::non_negative, default_value_t = 0.0)]
    pub th_theta: f64,
    /// `--param curve2d`: largest off-plane RMS accepted, as a fraction of the in-plane
    /// extent, in (0, 1).
    #[arg(long, value_parser = crate::cli::options::range::open_unit, default_value_t = 0.05)]
    pub max_plane_ratio: f64,
}

/// Arguments of `rgbid graph optimize`.
#[derive(clap::Args)]
pub struct OptimizeArgs {
    /// Input graph (.g2o, or iSAM .txt).
    pub input: PathBuf,
    /// Output g2o file.
    #[arg(long)]
    pub out: PathBuf,
    /// Solver settings.
    #[command(flatten)]
    pub solve: SolveArgs,
}

/// Which set of runs `rgbid graph bench` makes.
#[derive(Clone, Copy, Debug, clap::ValueEnum, PartialEq, Eq)]
pub enum Suite {
    /// Every file under `se-sync/`, `carlone/` and `isam/` with the given solver settings,
    /// against SE-Sync's f* and (with `--python`) GTSAM run on the same files in the same run.
    Files,
    /// The thesis' chapter-7 comparison (tables 7.1-7.4 analogues): SE(n), curve graph,
    /// curve graph with pseudo-Huber and linear 2D on Manhattan 3500 and its a/b/c variants,
    /// City10000, Intel, MIT, sphere2500, torus10000 and parking-garage, with position RMSE
    /// against `isam/groundtruth` where it exists; and the 3D-to-2D projection on the
    /// nearly planar KITTI graphs.
    Thesis,
}

/// Arguments of `rgbid graph bench`.
#[derive(clap::Args)]
pub struct BenchArgs {
    /// Folder holding `se-sync/`, `carlone/`, `isam/` (the shared pose-graph data).
    #[arg(long, default_value = "../shared/data/posegraph")]
    pub data: PathBuf,
    /// Which runs to make.
    #[arg(long, value_enum, default_value = "files")]
    pub suite: Suite,
    /// Only files whose name contains one of these strings.
    #[arg(long)]
    pub only: Vec<String>,
    /// Write the results as JSON (machine, commit, command and every row) to FILE, e.g.
    /// `docs/results/posegraph.json` for `scripts/results.py`; `--json` without FILE prints
    /// one JSON object per run instead of the table.
    #[arg(long, value_name = "FILE", num_args = 0..=1)]
    pub json: Option<Option<PathBuf>>,
    /// Time every rgbid solve this many times (>= 1) and report the median.
    #[arg(long, value_parser = crate::cli::options::range::at_least_one, default_value_t = 3)]
    pub repeat: usize,
    /// `--suite files`: Python with the `gtsam` wheel; runs `--peer-script` on every file in
    /// the same run (LM, GN and, in 3D, chordal + LM) and prints the time ratio against its
    /// best converged run. Without it the GTSAM figures of the data README are shown for
    /// reference (marked as not measured in the `--json` report).
    #[arg(long)]
    pub python: Option<String>,
    /// The GTSAM peer script.
    #[arg(long, default_value = "../shared/eval/peer_posegraph.py")]
    pub peer_script: PathBuf,
    /// Solver settings (`--suite files`; the thesis suite sets its own per method).
    #[command(flatten)]
    pub solve: SolveArgs,
}

/// Reads a g2o or iSAM file. The extension `.g2o` (any case) means g2o; otherwise the first
/// tag of the file decides (`VERTEX*`, `EDGE*` or `FIX` is g2o, anything else iSAM).
fn load(path: &Path) -> Result<G2oFile> {
    if is_g2o(path)? {
        Ok(read_g2o(path)?)
    } else {
        Ok(read_isam(path)?)
    }
}

fn is_g2o(path: &Path) -> Result<bool> {
    if path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("g2o"))
    {
        return Ok(true);
    }
    Ok(first_tag(path)?.is_some_and(|t| {
        let t = t.to_ascii_uppercase();
        t.starts_with("VERTEX") || t.starts_with("EDGE") || t == "FIX"
    }))
}

/// The first word of the first line that is neither empty nor a comment, from the first
/// 64 KiB of the file.
fn first_tag(path: &Path) -> Result<Option<String>> {
    use std::io::Read;
    let mut head = Vec::new();
    std::fs::File::open(path)
        .and_then(|f| f.take(64 * 1024).read_to_end(&mut head))
        .with_context(|| format!("cannot read {}", path.display()))?;
    let text = String::from_utf8_lossy(&head);
    let text = text.trim_start_matches('\u{feff}');
    Ok(text
        .lines()
        .map(str::trim)
        .find(|l| !l.is_empty() && !l.starts_with('#'))
        .and_then(|l| l.split_whitespace().next())
        .map(str::to_string))
}

impl SolveArgs {
    fn options(&self) -> SolverOptions {
        let kernel = match self.robust {
            RobustArg::None => None,
            RobustArg::Huber => Some(RobustKernel::Huber(self.robust_delta)),
            RobustArg::PseudoHuber => Some(RobustKernel::PseudoHuber(self.robust_delta)),
            RobustArg::Cauchy => Some(RobustKernel::Cauchy(self.robust_delta)),
        };
        SolverOptions {
            algorithm: match self.algorithm {
                AlgoArg::Lm => Algorithm::LevenbergMarquardt,
                AlgoArg::Gn => Algorithm::GaussNewton,
            },
            max_iterations: self.max_iterations,
            initial_lambda: self.initial_lambda.unwrap_or(match self.init {
                InitArg::Odometry => SolverOptions::default().initial_lambda,
                _ => 1e-9,
            }),
            kernel,
            ..Default::default()
        }
    }
    fn init(&self) -> InitMethod {
        match self.init {
            InitArg::Auto => InitMethod::Auto,
            InitArg::Odometry => InitMethod::Odometry,
            InitArg::Linear => InitMethod::Linear,
            InitArg::Chordal => InitMethod::Chordal,
        }
    }
}

/// Result of one solve, for printing.
pub struct Outcome {
    /// Seconds for initialisation (and, for curve graphs, building the curve graph).
    pub init_seconds: f64,
    /// Solver report.
    pub report: SolveReport,
    /// Final chi2 of the full poses (geodesic cost).
    pub chi2: f64,
    /// Final SE-Sync objective of the full poses.
    pub sesync_f: f64,
    /// Objective at the start (after reading).
    pub initial_f: f64,
    /// Number of optimised variables (poses, or curve nodes after reduction).
    pub variables: usize,
}

/// Optimises an SE(2) graph's positions as a curve graph and writes the full poses back.
fn solve_curve2(
    g: &mut graph::PoseGraph2,
    copts: &CurveOptions,
    opts: &SolverOptions,
) -> Result<(SolveReport, usize, f64)> {
    let t = Instant::now();
    let mut cg = CurveGraph2::new(g, copts)?;
    let build = t.elapsed().as_secs_f64();
    let report = cg.optimize(opts)?;
    g.poses = cg.poses();
    Ok((report, cg.kept.len(), build))
}

/// Initialises and optimises a loaded graph in place.
pub fn solve(graph: &mut LoadedGraph, args: &SolveArgs) -> Result<Outcome> {
    let opts = args.options();
    let copts = CurveOptions {
        th_d: args.th_d,
        th_theta: args.th_theta,
        ..Default::default()
    };
    let cost = match args.cost {
        CostArg::Geodesic => EdgeCost::Geodesic,
        CostArg::Sesync => EdgeCost::Chordal,
    };
    if cost != EdgeCost::Geodesic && args.param != Param::Se {
        bail!("--cost sesync applies to --param se only");
    }
    Ok(match graph {
        LoadedGraph::Se2(g) => {
            let initial_f = g.sesync_objective();
            let t = Instant::now();
            graph::initialize_2d(g, args.init())?;
            let mut init_seconds = t.elapsed().as_secs_f64();
            let (report, variables) = match args.param {
                Param::Se => (g.optimize_with(&opts, cost)?, g.poses.len()),
                Param::Curve => {
                    let (r, v, build) = solve_curve2(g, &copts, &opts)?;
                    init_seconds += build;
                    (r, v)
                }
                Param::Curve2d => bail!("--param curve2d projects 3D graphs; this one is 2D"),
            };
            Outcome {
                init_seconds,
                report,
                chi2: g.chi2(),
                sesync_f: g.sesync_objective(),
                initial_f,
                variables,
            }
        }
        LoadedGraph::Se3(g) => {
            let initial_f = g.sesync_objective();
            let t = Instant::now();
            graph::initialize_3d(g, args.init())?;
            let mut init_seconds = t.elapsed().as_secs_f64();
            let (report, variables) = match args.param {
                Param::Se => (g.optimize_with(&opts, cost)?, g.poses.len()),
                Param::Curve => {
                    let t = Instant::now();
                    let mut cg = CurveGraph3::new(g, &copts)?;
                    init_seconds += t.elapsed().as_secs_f64();
                    let r = cg.optimize(&opts)?;
                    g.poses = cg.poses();
                    (r, cg.kept.len())
                }
                Param::Curve2d => {
                    let t = Instant::now();
                    let (mut g2, pp) = planar::project_to_2d(g, args.max_plane_ratio)?;
                    init_seconds += t.elapsed().as_secs_f64();
                    let (r, v, build) = solve_curve2(&mut g2, &copts, &opts)?;
                    init_seconds += build;
                    g.poses = planar::lift_to_3d(g, &g2, &pp);
                    (r, v)
                }
            };
            Outcome {
                init_seconds,
                report,
                chi2: g.chi2(),
                sesync_f: g.sesync_objective(),
                initial_f,
                variables,
            }
        }
    })
}

/// Runs the subcommand.
pub fn run(c: Command) -> Result<()> {
    match c {
        Command::Optimize(a) => {
            super::outputs::output_file(&a.out, "--out", &[&a.input])?;
            let mut f = load(&a.input)?;
            let (nv, ne) = sizes(&f.graph);
            println!(
                "{}: {nv} vertices, {ne} edges{}",
                a.input.display(),
                if f.spanning_tree_initialised {
                    " (spanning-tree initial estimate)"
                } else {
                    ""
                }
            );
            if let Some(first) = f.repaired_information.first() {
                println!(
                    "warning: {} information matrices are not positive definite (first at line {first}); \
                     their translation-rotation cross blocks were dropped",
                    f.repaired_information.len()
                );
            }
            let o = solve(&mut f.graph, &a.solve)?;
            println!(
                "initial F {:.6e}  init {:.3} s",
                o.initial_f, o.init_seconds
            );
            for r in &o.report.history {
                println!(
                    "iter {:3}  cost {:.6e}  lambda {:.2e}  {}  {:.3} s",
                    r.iteration,
                    r.cost,
                    r.lambda,
                    if r.accepted { "accepted" } else { "rejected" },
                    r.seconds
                );
            }
            println!(
                "final: chi2 {:.6e}  F {:.6e}  variables {}  iterations {}  ({:?})  time {:.3} s (init {:.3} + solve {:.3})",
                o.chi2,
                o.sesync_f,
                o.variables,
                o.report.iterations,
                o.report.termination,
                o.init_seconds + o.report.seconds,
                o.init_seconds,
                o.report.seconds
            );
            write_g2o(&a.out, &f.graph)?;
            println!("wrote {}", a.out.display());
            // A solve stopped by the iteration limit wrote its last estimate, which is not an
            // optimum: exit code 3 (`--max-iterations 0` asks for the initialisation alone).
            if o.report.termination == Termination::MaxIterations && a.solve.max_iterations > 0 {
                return super::outcome::warnings(vec![format!(
                    "the solver stopped at --max-iterations {} without converging",
                    a.solve.max_iterations
                )]);
            }
            Ok(())
        }
        Command::Eval { est, gt } => {
            let e = load(&est)?;
            let g = load(&gt)?;
            let pe = positions(&e.graph);
            let pg = positions(&g.graph);
            let rmse = graph::eval::position_rmse(&pe, &pg).context("evaluating")?;
            println!(
                "position RMSE {rmse:.6} m over {} poses (rigidly aligned)",
                pe.len()
            );
            Ok(())
        }
        Command::Bench(a) => bench(&a),
    }
}

fn sizes(g: &LoadedGraph) -> (usize, usize) {
    match g {
        LoadedGraph::Se2(g) => (g.poses.len(), g.edges.len()),
        LoadedGraph::Se3(g) => (g.poses.len(), g.edges.len()),
    }
}

fn positions(g: &LoadedGraph) -> Vec<glam::DVec3> {
    match g {
        LoadedGraph::Se2(g) => g.positions(),
        LoadedGraph::Se3(g) => g.positions(),
    }
}

/// Globally optimal SE-Sync objective values (Rosen et al., IJRR 2019), from the data README.
const FSTAR: &[(&str, f64)] = &[
    ("se-sync/manhattan.g2o", 6.432e3),
    ("se-sync/city10000.g2o", 6.386e2),
    ("se-sync/CSAIL.g2o", 3.170e1),
    ("se-sync/intel.g2o", 5.235e1),
    ("se-sync/ais2klinik.g2o", 1.885e2),
    ("se-sync/sphere2500.g2o", 1.687e3),
    ("se-sync/torus3D.g2o", 2.423e4),
    ("se-sync/parking-garage.g2o", 1.263e0),
    ("se-sync/cubicle.g2o", 7.171e2),
];

/// GTSAM 4 LM from the file's initial values, as listed in the data README (F, chi2, s).
const GTSAM_README: &[(&str, f64, f64, f64)] = &[
    ("se-sync/intel.g2o", 54.50, 45.00, 0.08),
    ("se-sync/manhattan.g2o", 6610.0, 3549.0, 0.24),
    ("se-sync/city10000.g2o", 649.4, 512.0, 1.3),
    ("se-sync/sphere2500.g2o", 1730.0, 1351.4, 0.8),
    ("se-sync/parking-garage.g2o", 1.266, 1.268, 0.35),
    ("se-sync/torus3D.g2o", 57960.0, 59908.0, 26.3),
    ("se-sync/cubicle.g2o", 2568.0, 2746.0, 22.9),
    ("carlone/M3500b.g2o", 48697.0, 45308.0, 11.1),
    ("carlone/M3500c.g2o", 12110.0, 8127.0, 7.2),
];

fn file_key(path: &Path) -> String {
    let name = |p: Option<&std::ffi::OsStr>| {
        p.map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default()
    };
    format!(
        "{}/{}",
        name(path.parent().and_then(|p| p.file_name())),
        name(path.file_name())
    )
}

/// Loads and solves `repeat` times; returns the last outcome (with the median total time in
/// `report.seconds` and zero `init_seconds`), the final graph and the vertex/edge counts.
fn solve_timed(
    path: &Path,
    args: &SolveArgs,
    repeat: usize,
) -> Result<(Outcome, LoadedGraph, usize, usize)> {
    solve_timed_with(&|| Ok(load(path)?.graph), args, repeat)
}

/// [`solve_timed`] on a graph made by `make` (called once per repeat).
fn solve_timed_with(
    make: &dyn Fn() -> Result<LoadedGraph>,
    args: &SolveArgs,
    repeat: usize,
) -> Result<(Outcome, LoadedGraph, usize, usize)> {
    let mut times = Vec::new();
    let mut last = None;
    for _ in 0..repeat.max(1) {
        let mut g = make()?;
        let (nv, ne) = sizes(&g);
        let o = solve(&mut g, args)?;
        times.push(o.init_seconds + o.report.seconds);
        last = Some((o, g, nv, ne));
    }
    let (mut o, g, nv, ne) = last.context("no run")?;
    o.report.seconds = crate::cli::bench::median(&mut times);
    o.init_seconds = 0.0;
    Ok((o, g, nv, ne))
}

/// GTSAM's runs on one file from the peer script: `(method, seconds, chi2, F)` per
/// successful run.
fn run_gtsam(python: &str, script: &Path, file: &Path) -> Result<Vec<(String, f64, f64, f64)>> {
    Ok(
        rgbid::experiments::peers::run_graph_peer(python, script, file)?
            .into_iter()
            .map(|r| (r.method, r.seconds, r.chi2, r.sesync_objective))
            .collect(),
    )
}

fn bench_files(a: &BenchArgs) -> Result<Vec<PathBuf>> {
    let mut files = Vec::new();
    for sub in ["se-sync", "carlone", "isam"] {
        let dir = a.data.join(sub);
        let Ok(rd) = std::fs::read_dir(&dir) else {
            continue;
        };
        let mut names: Vec<PathBuf> = rd
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.is_file())
            .collect();
        names.sort();
        files.extend(names);
    }
    if files.is_empty() {
        bail!("no pose-graph files under {}", a.data.display());
    }
    files.retain(|p| a.only.is_empty() || a.only.iter().any(|o| file_key(p).contains(o.as_str())));
    Ok(files)
}

/// GTSAM's result on one file, for the `--json` report.
#[derive(serde::Serialize)]
struct GtsamRun {
    /// `gtsam_lm`, `gtsam_gn`, `gtsam_chordal+lm`, or `README` for the data README's figures.
    method: String,
    /// Wall time, seconds.
    s: f64,
    chi2: f64,
    /// SE-Sync objective.
    #[serde(rename = "F")]
    f: f64,
}

/// One file of `graph bench --suite files`, for the `--json` report.
#[derive(serde::Serialize)]
struct FileRow {
    file: String,
    poses: usize,
    edges: usize,
    iterations: usize,
    /// Median seconds of the rgbid solves (initialisation included).
    s: f64,
    chi2: f64,
    /// SE-Sync objective of the result.
    #[serde(rename = "F")]
    f: f64,
    /// SE-Sync's certified optimum of F, where published.
    fstar: Option<f64>,
    termination: String,
    /// True when the GTSAM figures were measured in this run (false: the data README's).
    gtsam_measured: bool,
    /// GTSAM's run with the lowest chi2.
    gtsam: Option<GtsamRun>,
    /// Every GTSAM run of this benchmark on the file (measured runs only).
    gtsam_runs: Vec<GtsamRun>,
    /// GTSAM's seconds over rgbid's (> 1: rgbid is faster).
    speedup_vs_gtsam: Option<f64>,
}

/// One (file, method) of `graph bench --suite thesis`, for the `--json` report.
#[derive(serde::Serialize)]
struct ThesisRow {
    file: String,
    method: String,
    variables: usize,
    iterations: usize,
    s: f64,
    chi2: f64,
    #[serde(rename = "F")]
    f: f64,
    /// Position RMSE against the ground truth after rigid alignment, m.
    rmse_gt_m: Option<f64>,
    /// Position RMSE against this run's SE(n) linear/chordal solution, m.
    rmse_vs_se_m: Option<f64>,
}

fn bench(a: &BenchArgs) -> Result<()> {
    match a.suite {
        Suite::Files => bench_suite_files(a),
        Suite::Thesis => bench_suite_thesis(a),
    }
}

/// Writes the `--json FILE` report of either suite.
fn write_bench_report(a: &BenchArgs, path: &Path, rows: &impl serde::Serialize) -> Result<()> {
    let gtsam_version = a
        .python
        .as_deref()
        .filter(|_| a.suite == Suite::Files)
        .and_then(|py| super::report::python_module_version(py, "gtsam"));
    let body = serde_json::json!({
        "suite": format!("{:?}", a.suite).to_lowercase(),
        "data": a.data.display().to_string(),
        "repeat": a.repeat.max(1),
        "solver": {
            "param": format!("{:?}", a.solve.param),
            "cost": format!("{:?}", a.solve.cost),
            "init": format!("{:?}", a.solve.init),
            "algorithm": format!("{:?}", a.solve.algorithm),
            "robust": format!("{:?}", a.solve.robust),
        },
        "peer_versions": gtsam_version.map(|v| serde_json::json!({"gtsam": v})).unwrap_or_else(|| serde_json::json!({})),
        "rows": rows,
    });
    super::report::write(path, "posegraph", &super::report::meta(Vec::new()), &body)
}

fn bench_suite_files(a: &BenchArgs) -> Result<()> {
    let files = bench_files(a)?;
    let json_lines = matches!(a.json, Some(None));
    let mut report_rows = Vec::new();
    if !json_lines {
        println!(
            "rgbid: median of {} solves, --param {:?} --cost {:?} --init {:?}; GTSAM: {}",
            a.repeat.max(1),
            a.solve.param,
            a.solve.cost,
            a.solve.init,
            if a.python.is_some() {
                "best converged run of LM / GN / chordal+LM, measured now"
            } else {
                "figures from the data README (pass --python to measure)"
            }
        );
        println!(
            "{:<34} {:>6} {:>6} {:>5} {:>8} {:>12} {:>12} {:>7} | {:>10} {:>10} {:>8} {:>14} {:>7}",
            "file",
            "poses",
            "edges",
            "iter",
            "s",
            "chi2",
            "F",
            "F/f*",
            "GTSAM chi2",
            "GTSAM F",
            "GTSAM s",
            "GTSAM run",
            "speedup"
        );
    }
    let pb = indicatif::ProgressBar::new(files.len() as u64);
    for path in files {
        let key = file_key(&path);
        let (o, _, nv, ne) = match solve_timed(&path, &a.solve, a.repeat) {
            Ok(x) => x,
            Err(e) => {
                pb.suspend(|| eprintln!("{key}: {e:#}"));
                pb.inc(1);
                continue;
            }
        };
        let total = o.report.seconds;
        let fstar = FSTAR.iter().find(|(k, _)| *k == key).map(|x| x.1);
        // GTSAM: the run with the lowest chi2 (measured now), or the data README figure.
        let mut gtsam_runs = Vec::new();
        let gtsam: Option<(String, f64, f64, f64)> = match &a.python {
            Some(py) => match run_gtsam(py, &a.peer_script, &path) {
                Ok(runs) => {
                    gtsam_runs.clone_from(&runs);
                    runs.into_iter()
                        .filter(|r| r.2.is_finite())
                        .min_by(|x, y| x.2.total_cmp(&y.2))
                }
                Err(e) => {
                    pb.suspend(|| eprintln!("{key}: GTSAM: {e:#}"));
                    None
                }
            },
            None => GTSAM_README
                .iter()
                .find(|(k, ..)| *k == key)
                .map(|g| ("README".to_string(), g.3, g.2, g.1)),
        };
        let as_run = |g: &(String, f64, f64, f64)| GtsamRun {
            method: g.0.clone(),
            s: g.1,
            chi2: g.2,
            f: g.3,
        };
        report_rows.push(FileRow {
            file: key.clone(),
            poses: nv,
            edges: ne,
            iterations: o.report.iterations,
            s: total,
            chi2: o.chi2,
            f: o.sesync_f,
            fstar,
            termination: format!("{:?}", o.report.termination),
            gtsam_measured: a.python.is_some() && gtsam.is_some(),
            gtsam: gtsam.as_ref().map(as_run),
            gtsam_runs: gtsam_runs.iter().map(as_run).collect(),
            speedup_vs_gtsam: gtsam.as_ref().map(|g| g.1 / total),
        });
        if json_lines {
            let line = serde_json::json!({
                "file": key, "poses": nv, "edges": ne, "s": total,
                "iterations": o.report.iterations, "chi2": o.chi2, "F": o.sesync_f, "fstar": fstar,
                "termination": format!("{:?}", o.report.termination),
                "gtsam": gtsam.as_ref().map(|g| serde_json::json!({"method": g.0, "s": g.1, "chi2": g.2, "F": g.3})),
            })
            .to_string();
            pb.suspend(|| println!("{line}"));
        } else {
            let ratio = fstar
                .map(|f| format!("{:.4}", o.sesync_f / f))
                .unwrap_or_else(|| "-".into());
            let (gc, gf, gs, gm, sp) = gtsam
                .map(|g| {
                    (
                        format!("{:.4e}", g.2),
                        format!("{:.4e}", g.3),
                        format!("{:.3}", g.1),
                        g.0.clone(),
                        format!("{:.2}x", g.1 / total),
                    )
                })
                .unwrap_or_else(|| ("-".into(), "-".into(), "-".into(), "-".into(), "-".into()));
            pb.suspend(|| {
                println!(
                    "{:<34} {:>6} {:>6} {:>5} {:>8.3} {:>12.5e} {:>12.5e} {:>7} | {:>10} {:>10} {:>8} {:>14} {:>7}",
                    key, nv, ne, o.report.iterations, total, o.chi2, o.sesync_f, ratio, gc, gf, gs, gm, sp
                )
            });
        }
        pb.inc(1);
    }
    pb.finish_and_clear();
    if let Some(Some(path)) = &a.json {
        write_bench_report(a, path, &report_rows)?;
    }
    Ok(())
}

/// Runs every method on one dataset of the thesis suite and prints its rows.
fn thesis_rows(
    a: &BenchArgs,
    file: &str,
    make: &dyn Fn() -> Result<LoadedGraph>,
    gt_pos: Option<Vec<glam::DVec3>>,
    methods: &[(&str, SolveArgs, Option<bool>)],
    report_rows: &mut Vec<ThesisRow>,
) -> Result<()> {
    let is3d = matches!(make()?, LoadedGraph::Se3(_));
    let mut reference: Option<Vec<glam::DVec3>> = None;
    for (label, args, only) in methods {
        if only.is_some_and(|want3| want3 != is3d) {
            continue;
        }
        let (o, g, _, _) = match solve_timed_with(make, args, a.repeat) {
            Ok(x) => x,
            Err(e) => {
                println!("{file:<28} {label:<36} failed: {e:#}");
                continue;
            }
        };
        let pos = positions(&g);
        let rmse = |other: &Option<Vec<glam::DVec3>>| {
            other
                .as_ref()
                .and_then(|r| graph::eval::position_rmse(&pos, r).ok())
        };
        let (rmse_gt_m, rmse_vs_se_m) = (rmse(&gt_pos), rmse(&reference));
        let text = |v: Option<f64>| v.map_or_else(|| "-".into(), |v| format!("{v:.4}"));
        let (r_gt, r_se) = (text(rmse_gt_m), text(rmse_vs_se_m));
        if *label == "SE(n) linear/chordal init" {
            reference = Some(pos.clone());
        }
        report_rows.push(ThesisRow {
            file: file.to_string(),
            method: label.to_string(),
            variables: o.variables,
            iterations: o.report.iterations,
            s: o.report.seconds,
            chi2: o.chi2,
            f: o.sesync_f,
            rmse_gt_m,
            rmse_vs_se_m,
        });
        if matches!(a.json, Some(None)) {
            println!(
                "{}",
                serde_json::json!({"file": file, "method": label, "variables": o.variables,
                    "iterations": o.report.iterations, "s": o.report.seconds, "chi2": o.chi2,
                    "F": o.sesync_f, "rmse_gt": r_gt, "rmse_vs_se": r_se})
            );
        } else {
            println!(
                "{:<28} {:<36} {:>6} {:>5} {:>8.3} {:>12.5e} {:>10} {:>10}",
                file, label, o.variables, o.report.iterations, o.report.seconds, o.chi2, r_gt, r_se
            );
        }
    }
    Ok(())
}

fn bench_suite_thesis(a: &BenchArgs) -> Result<()> {
    let base = SolveArgs {
        param: Param::Se,
        init: InitArg::Auto,
        algorithm: AlgoArg::Lm,
        robust: RobustArg::None,
        robust_delta: 1.0,
        max_iterations: 500,
        initial_lambda: None,
        cost: CostArg::Geodesic,
        th_d: 0.0,
        th_theta: 0.0,
        max_plane_ratio: 0.05,
    };
    let with = |f: &dyn Fn(&mut SolveArgs)| {
        let mut s = base.clone();
        f(&mut s);
        s
    };
    // (label, settings, only for 2D / 3D)
    let methods: Vec<(&str, SolveArgs, Option<bool>)> = vec![
        (
            "SE(n) from odometry",
            with(&|s| s.init = InitArg::Odometry),
            None,
        ),
        ("SE(n) linear/chordal init", base.clone(), None),
        (
            "linear 2D (no iterations)",
            with(&|s| s.max_iterations = 0),
            Some(false),
        ),
        (
            "curve R^n from odometry",
            with(&|s| {
                s.param = Param::Curve;
                s.init = InitArg::Odometry;
            }),
            None,
        ),
        (
            "curve R^n + pseudo-Huber",
            with(&|s| {
                s.param = Param::Curve;
                s.init = InitArg::Odometry;
                s.robust = RobustArg::PseudoHuber;
            }),
            None,
        ),
        (
            "curve R^n from linear/chordal",
            with(&|s| s.param = Param::Curve),
            None,
        ),
        (
            "curve R^n reduced (th_d 0.5 m)",
            with(&|s| {
                s.param = Param::Curve;
                s.th_d = 0.5;
            }),
            None,
        ),
        (
            "curve R^2 of the 3D graph projected",
            with(&|s| s.param = Param::Curve2d),
            Some(true),
        ),
    ];
    println!(
        "median of {} solves per row; RMSE: positions against isam/groundtruth after rigid alignment; \
         'vs SE' : position RMSE against this run's SE(n) linear/chordal solution",
        a.repeat.max(1)
    );
    println!(
        "{:<28} {:<36} {:>6} {:>5} {:>8} {:>12} {:>10} {:>10}",
        "file", "method", "vars", "iter", "s", "chi2", "RMSE m", "vs SE m"
    );
    let mut report_rows = Vec::new();
    for (file, gt) in rgbid::experiments::graph::THESIS_DATA {
        if !a.only.is_empty() && !a.only.iter().any(|o| file.contains(o.as_str())) {
            continue;
        }
        let path = a.data.join(file);
        if !path.exists() {
            eprintln!("{file}: missing, skipped");
            continue;
        }
        let gt_pos = match gt {
            Some(g) => Some(positions(&load(&a.data.join(g))?.graph)),
            None => None,
        };
        thesis_rows(
            a,
            file,
            &|| Ok(load(&path)?.graph),
            gt_pos,
            &methods,
            &mut report_rows,
        )?;
    }
    // The projection experiment of 7.4.6 with ground truth: M3500 laid on a tilted plane in
    // 3D, with small out-of-plane noise on every measurement.
    let tilted = "M3500 on a tilted plane (3D)";
    if a.only.is_empty() || a.only.iter().any(|o| tilted.contains(o.as_str())) {
        let m3500 = a.data.join("carlone/M3500.g2o");
        let gt = a
            .data
            .join("isam/groundtruth/manhattanOlson3500_groundtruth.txt");
        if m3500.exists() && gt.exists() {
            let gt2 = positions(&load(&gt)?.graph);
            let (r0, t0) = rgbid::experiments::graph::tilt();
            let gt3: Vec<glam::DVec3> = gt2.iter().map(|p| r0 * *p + t0).collect();
            let make = || {
                let LoadedGraph::Se2(g2) = load(&m3500)?.graph else {
                    bail!("{} is not a 2D graph", m3500.display());
                };
                Ok(LoadedGraph::Se3(
                    rgbid::experiments::graph::lift_to_tilted_plane(&g2)?,
                ))
            };
            thesis_rows(a, tilted, &make, Some(gt3), &methods, &mut report_rows)?;
        }
    }
    if let Some(Some(path)) = &a.json {
        write_bench_report(a, path, &report_rows)?;
    }
    Ok(())
}
