//! `rgbid graph`: pose-graph optimisation, evaluation and benchmarks (thesis ch. 7).

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use rgbid::graph::{self, Algorithm, InitMethod, RobustKernel, SolveReport, SolverOptions};
use rgbid::io::g2o::{read_g2o, write_g2o, G2oFile, LoadedGraph};
use rgbid::io::isam::read_isam;

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
    /// Kernel width (on the whitened residual norm).
    #[arg(long, default_value_t = 1.0)]
    pub robust_delta: f64,
    /// Maximum iterations.
    #[arg(long, default_value_t = 100)]
    pub max_iterations: usize,
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

/// Arguments of `rgbid graph bench`.
#[derive(clap::Args)]
pub struct BenchArgs {
    /// Folder holding `se-sync/`, `carlone/`, `isam/` (the shared pose-graph data).
    #[arg(long, default_value = "../shared/data/posegraph")]
    pub data: PathBuf,
    /// Only files whose name contains one of these strings.
    #[arg(long)]
    pub only: Vec<String>,
    /// Print one JSON object per file instead of the table.
    #[arg(long)]
    pub json: bool,
    /// Solver settings.
    #[command(flatten)]
    pub solve: SolveArgs,
}

fn load(path: &Path) -> Result<G2oFile> {
    let is_g2o = path.extension().is_some_and(|e| e == "g2o");
    if is_g2o {
        Ok(read_g2o(path)?)
    } else {
        Ok(read_isam(path)?)
    }
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
    /// Seconds for initialisation.
    pub init_seconds: f64,
    /// Solver report.
    pub report: SolveReport,
    /// Final chi2.
    pub chi2: f64,
    /// Final SE-Sync objective.
    pub sesync_f: f64,
    /// Objective at the start (after reading).
    pub initial_f: f64,
}

/// Initialises and optimises a loaded graph in place.
pub fn solve(graph: &mut LoadedGraph, args: &SolveArgs) -> Result<Outcome> {
    let opts = args.options();
    match args.param {
        Param::Se => {}
    }
    Ok(match graph {
        LoadedGraph::Se2(g) => {
            let initial_f = g.sesync_objective();
            let t = Instant::now();
            graph::initialize_2d(g, args.init())?;
            let init_seconds = t.elapsed().as_secs_f64();
            let report = g.optimize(&opts)?;
            Outcome {
                init_seconds,
                report,
                chi2: g.chi2(),
                sesync_f: g.sesync_objective(),
                initial_f,
            }
        }
        LoadedGraph::Se3(g) => {
            let initial_f = g.sesync_objective();
            let t = Instant::now();
            graph::initialize_3d(g, args.init())?;
            let init_seconds = t.elapsed().as_secs_f64();
            let report = g.optimize(&opts)?;
            Outcome {
                init_seconds,
                report,
                chi2: g.chi2(),
                sesync_f: g.sesync_objective(),
                initial_f,
            }
        }
    })
}

/// Runs the subcommand.
pub fn run(c: Command) -> Result<()> {
    match c {
        Command::Optimize(a) => {
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
                "final: chi2 {:.6e}  F {:.6e}  iterations {}  ({:?})  time {:.3} s (init {:.3} + solve {:.3})",
                o.chi2,
                o.sesync_f,
                o.report.iterations,
                o.report.termination,
                o.init_seconds + o.report.seconds,
                o.init_seconds,
                o.report.seconds
            );
            write_g2o(&a.out, &f.graph)?;
            println!("wrote {}", a.out.display());
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

fn bench(a: &BenchArgs) -> Result<()> {
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
    if !a.json {
        println!(
            "{:<34} {:>6} {:>6} {:>8} {:>7} {:>5} {:>12} {:>12} {:>9} | {:>10} {:>10} {:>7}",
            "file",
            "poses",
            "edges",
            "init s",
            "total s",
            "iter",
            "chi2",
            "F",
            "F/f*",
            "GTSAM F",
            "GTSAM chi2",
            "GTSAM s"
        );
    }
    let pb = indicatif::ProgressBar::new(files.len() as u64);
    for path in files {
        let key = format!(
            "{}/{}",
            path.parent()
                .and_then(|p| p.file_name())
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_default(),
            path.file_name()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_default()
        );
        if !a.only.is_empty() && !a.only.iter().any(|o| key.contains(o.as_str())) {
            pb.inc(1);
            continue;
        }
        let mut f = match load(&path) {
            Ok(f) => f,
            Err(e) => {
                pb.println(format!("{key}: {e:#}"));
                pb.inc(1);
                continue;
            }
        };
        let (nv, ne) = sizes(&f.graph);
        let o = match solve(&mut f.graph, &a.solve) {
            Ok(o) => o,
            Err(e) => {
                pb.println(format!("{key}: {e:#}"));
                pb.inc(1);
                continue;
            }
        };
        let total = o.init_seconds + o.report.seconds;
        let fstar = FSTAR.iter().find(|(k, _)| *k == key).map(|x| x.1);
        let gt = GTSAM_README.iter().find(|(k, ..)| *k == key);
        if a.json {
            pb.println(
                serde_json::json!({
                    "file": key, "poses": nv, "edges": ne, "init_s": o.init_seconds, "s": total,
                    "iterations": o.report.iterations, "chi2": o.chi2, "F": o.sesync_f, "fstar": fstar,
                    "termination": format!("{:?}", o.report.termination),
                })
                .to_string(),
            );
        } else {
            let ratio = fstar
                .map(|f| format!("{:.4}", o.sesync_f / f))
                .unwrap_or_else(|| "-".into());
            let (gf, gc, gs) = gt
                .map(|g| {
                    (
                        format!("{:.4e}", g.1),
                        format!("{:.4e}", g.2),
                        format!("{:.2}", g.3),
                    )
                })
                .unwrap_or_else(|| ("-".into(), "-".into(), "-".into()));
            pb.println(format!(
                "{:<34} {:>6} {:>6} {:>8.3} {:>7.3} {:>5} {:>12.5e} {:>12.5e} {:>9} | {:>10} {:>10} {:>7}",
                key, nv, ne, o.init_seconds, total, o.report.iterations, o.chi2, o.sesync_f, ratio, gf, gc, gs
            ));
        }
        pb.inc(1);
    }
    pb.finish_and_clear();
    Ok(())
}
