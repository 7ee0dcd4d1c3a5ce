//! `rgbid export IN --format F --out PATH`: a run folder's or a map file's trajectory, model or
//! pose graph in the format another tool reads.
//!
//! | format | from a run folder (`rgbid slam --out`) | from a map file (`rgbid slam --map-out`) |
//! |---|---|---|
//! | `tum`, `kitti`, `euroc` | `trajectory.txt` (`--keyframes`: `keyframes.txt`) | keyframe poses |
//! | `ply`, `obj` | `model.ply` | the model rebuilt from the keyframes |
//! | `g2o` | no graph is stored there: an error says to export the map | keyframe poses and graph edges |

use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use glam::DVec3;
use rgbid::graph::g2o::{write_g2o, LoadedGraph};
use rgbid::graph::PoseGraph3;
use rgbid::io::run_folder::RunFolder;
use rgbid::io::trajectory::{write_trajectory, TrajectoryFormat};
use rgbid::slam::{build_coloured_model, Map, ModelParams};
use rgbid::trajectory::TimedPose;

/// Output formats of `rgbid export`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Format {
    /// TUM trajectory: `timestamp tx ty tz qx qy qz qw`.
    Tum,
    /// KITTI trajectory: 3x4 rows, time stamps in `<stem>.times.txt` beside.
    Kitti,
    /// EuRoC CSV trajectory: nanoseconds, quaternion w first.
    Euroc,
    /// Point cloud as binary PLY with RGB colour per vertex.
    Ply,
    /// Point cloud as OBJ `v x y z r g b` lines (colour in 0..1, as MeshLab and Open3D read).
    Obj,
    /// Keyframe pose graph: `VERTEX_SE3:QUAT` and `EDGE_SE3:QUAT` lines, the first vertex fixed.
    G2o,
}

/// Arguments of `rgbid export`.
#[derive(clap::Args)]
pub struct Args {
    /// A run folder (written by `rgbid slam --out`) or a map file (`rgbid slam --map-out`).
    pub input: PathBuf,
    /// Output format.
    #[arg(long, value_enum)]
    pub format: Format,
    /// Output file.
    #[arg(long, short)]
    pub out: PathBuf,
    /// Trajectory formats from a run folder: the keyframe poses instead of every frame's.
    #[arg(long)]
    pub keyframes: bool,
    /// Model from a map: voxel size of the filter, metres, >= 0 (0 keeps every point).
    #[arg(long, value_parser = crate::cli::options::range::non_negative, default_value_t = ModelParams::default().voxel)]
    pub voxel: f64,
}

/// What was read.
enum Input {
    Run(Box<RunFolder>),
    Map(Box<Map>),
}

/// Runs the subcommand.
pub fn run(args: Args) -> Result<()> {
    let input = if args.input.is_dir() {
        if !RunFolder::is_run_folder(&args.input) {
            bail!(
                "{} is a folder without summary.json: not a run folder of `rgbid slam --out`",
                args.input.display()
            );
        }
        Input::Run(Box::new(RunFolder::read(&args.input)?))
    } else {
        Input::Map(Box::new(Map::load(&args.input).with_context(|| {
            format!("reading map {}", args.input.display())
        })?))
    };
    if args.out == args.input {
        bail!("--out {} is the input", args.out.display());
    }
    let written = match args.format {
        Format::Tum | Format::Kitti | Format::Euroc => {
            let format = match args.format {
                Format::Kitti => TrajectoryFormat::Kitti,
                Format::Euroc => TrajectoryFormat::Euroc,
                _ => TrajectoryFormat::Tum,
            };
            let poses = trajectory(&input, args.keyframes)?;
            write_trajectory(&args.out, &poses, format)?;
            format!("{} poses", poses.len())
        }
        Format::Ply | Format::Obj => {
            let points = model(&input, args.voxel)?;
            if points.is_empty() {
                bail!("{}: the model has no points", args.input.display());
            }
            if args.format == Format::Ply {
                rgbid::io::ply::write_ply(&args.out, &points)?;
            } else {
                write_obj(&args.out, &points)?;
            }
            format!("{} points", points.len())
        }
        Format::G2o => {
            let Input::Map(map) = &input else {
                bail!(
                    "a run folder holds no pose graph: export the map written by \
                     `rgbid slam --map-out MAP` (`rgbid export MAP --format g2o`)"
                );
            };
            let graph = pose_graph(map)?;
            let (v, e) = (graph.poses.len(), graph.edges.len());
            write_g2o(&args.out, &LoadedGraph::Se3(graph))?;
            format!("{v} vertices, {e} edges")
        }
    };
    println!("wrote {} ({written})", args.out.display());
    Ok(())
}

/// The poses to write: a run folder's trajectory (or keyframes), a map's keyframe poses.
fn trajectory(input: &Input, keyframes: bool) -> Result<Vec<TimedPose>> {
    let poses = match input {
        Input::Run(run) if keyframes => run.keyframes.clone(),
        Input::Run(run) => run.trajectory.clone(),
        Input::Map(map) => map
            .keyframes
            .iter()
            .map(|k| TimedPose {
                timestamp: k.timestamp,
                world_from_camera: k.world_from_keyframe,
            })
            .collect(),
    };
    if poses.is_empty() {
        bail!("no poses to export (the run wrote no trajectory yet?)");
    }
    Ok(poses)
}

/// World points (metres) with their colour: a run folder's model (as `model.ply` holds it), or
/// a map's model rebuilt from its keyframes at their optimised poses (keyframe colour, grey
/// for keyframes without colour).
fn model(input: &Input, voxel: f64) -> Result<Vec<(DVec3, [u8; 3])>> {
    Ok(match input {
        Input::Run(run) => {
            let path = run.dir.join(rgbid::io::run_folder::files::MODEL);
            if path.is_file() {
                rgbid::io::ply::read_ply(&path)?
            } else {
                Vec::new()
            }
        }
        Input::Map(map) => {
            let poses: Vec<_> = map
                .keyframes
                .iter()
                .map(|k| k.world_from_keyframe)
                .collect();
            let params = ModelParams {
                voxel,
                ..ModelParams::default()
            };
            build_coloured_model(&map.keyframes, &poses, &map.camera, &params)
        }
    })
}

/// The map's keyframe graph: vertices at the optimised poses (ids as in the map), the map's
/// edges with their information, the first keyframe fixed (the gauge).
fn pose_graph(map: &Map) -> Result<PoseGraph3> {
    let mut g = PoseGraph3::new();
    for k in &map.keyframes {
        g.add_vertex(k.id as i64, k.world_from_keyframe)?;
    }
    for e in &map.edges {
        g.add_edge(
            e.from as i64,
            e.to as i64,
            e.measurement,
            e.information.clone(),
        )
        .with_context(|| format!("map edge {} -> {}", e.from, e.to))?;
    }
    if let Some(f) = g.fixed.first_mut() {
        *f = true;
    }
    Ok(g)
}

/// Writes points as OBJ vertices with colour.
fn write_obj(path: &Path, points: &[(DVec3, [u8; 3])]) -> Result<()> {
    let file =
        std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?;
    let mut w = std::io::BufWriter::new(file);
    let io = |e| anyhow::Error::from(e).context(format!("writing {}", path.display()));
    writeln!(
        w,
        "# rgbid point cloud: {} vertices, world frame, metres",
        points.len()
    )
    .map_err(io)?;
    for (p, c) in points {
        let [r, g, b] = c.map(|v| f64::from(v) / 255.0);
        writeln!(w, "v {} {} {} {r:.4} {g:.4} {b:.4}", p.x, p.y, p.z).map_err(io)?;
    }
    w.flush().map_err(io)?;
    Ok(())
}
