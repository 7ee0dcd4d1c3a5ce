//! Showing what `rgbid slam` wrote (a run folder, read by the library's
//! [`rgbid::io::run_folder`], with the colours of its `model.ply` and its `mesh.ply`) and
//! saved maps.

use std::path::Path;

use anyhow::{Context, Result};
use std::sync::Arc;

use rgbid::io::ply::{read_mesh_ply, read_ply};
use rgbid::io::run_folder::{files, FrameRow, RunFolder};
use rgbid::slam::{build_coloured_model, Map, ModelParams};
use rgbid::trajectory::TimedPose;

use crate::worker::FinishedRun;

/// A diagnostic value of a frame row, NaN where the front-end did not fill it (missing, or 0
/// on lost frames), so plots leave it out.
pub fn known(v: Option<f64>) -> f64 {
    match v {
        Some(v) if v > 0.0 && v.is_finite() => v,
        _ => f64::NAN,
    }
}

/// Everything shown from a finished output folder.
#[derive(Clone, Debug, Default)]
pub struct OutputFolder {
    /// Trajectory, keyframes, loops, model.
    pub run: FinishedRun,
    /// Ground truth, if groundtruth.txt exists.
    pub groundtruth: Option<Vec<TimedPose>>,
    /// Per-frame statistics, if timing.csv exists.
    pub stages: Vec<FrameRow>,
}

/// File name of the mesh in a run folder (`rgbid slam --mesh`).
pub const MESH_FILE: &str = "mesh.ply";

/// Whether a model has colour from colour images: some point's channels differ (a model of a
/// run without colour is grey, red = green = blue).
pub fn is_coloured(model: &[(glam::DVec3, [u8; 3])]) -> bool {
    model.iter().any(|(_, c)| c[0] != c[1] || c[1] != c[2])
}

/// Loads an output folder of `rgbid slam` (see [`RunFolder::read`]: a trajectory is required,
/// the rest optional; an interrupted run shows its front-end trajectory), with the RGB
/// colours of `model.ply` and the mesh `mesh.ply` when there is one.
pub fn load_output(dir: &Path) -> Result<OutputFolder> {
    let folder = RunFolder::read(dir)
        .with_context(|| format!("{} is not a readable rgbid slam run folder", dir.display()))?;
    // The library's reader keeps the model grey; the viewer shows its colours.
    let model_path = dir.join(files::MODEL);
    let model = if model_path.is_file() {
        read_ply(&model_path)?
    } else {
        Vec::new()
    };
    let mesh_path = dir.join(MESH_FILE);
    let mesh = if mesh_path.is_file() {
        Some(Arc::new(read_mesh_ply(&mesh_path)?))
    } else {
        None
    };
    let coloured = is_coloured(&model) || mesh.as_ref().is_some_and(|m| is_coloured(&m.vertices));
    let n = folder.keyframes.len();
    let loops = folder
        .loops
        .iter()
        .filter(|l| l.accepted && !l.relocalisation && l.query < n && l.candidate < n)
        .map(|l| (l.query, l.candidate))
        .collect();
    Ok(OutputFolder {
        stages: folder.frames,
        groundtruth: folder.groundtruth,
        run: FinishedRun {
            trajectory: folder.trajectory,
            keyframes: folder.keyframes,
            loops,
            model,
            coloured,
            mesh,
            final_optimise_ms: 0.0,
        },
    })
}

/// Loads a saved map: keyframe poses, map edges between non-consecutive keyframes (loops)
/// and the voxel-filtered model of its keyframes.
pub fn load_map(path: &Path, voxel: f64) -> Result<FinishedRun> {
    let map = Map::load(path).with_context(|| format!("loading map {}", path.display()))?;
    let poses: Vec<_> = map
        .keyframes
        .iter()
        .map(|k| k.world_from_keyframe)
        .collect();
    let model = build_coloured_model(
        &map.keyframes,
        &poses,
        &map.camera,
        &ModelParams {
            voxel,
            ..ModelParams::default()
        },
    );
    let coloured = map.keyframes.iter().any(|k| k.colour.is_some());
    let keyframes: Vec<TimedPose> = map
        .keyframes
        .iter()
        .map(|k| TimedPose {
            timestamp: k.timestamp,
            world_from_camera: k.world_from_keyframe,
        })
        .collect();
    let loops = map
        .edges
        .iter()
        .filter(|e| e.from.abs_diff(e.to) > 1 && e.from < keyframes.len() && e.to < keyframes.len())
        .map(|e| (e.from, e.to))
        .collect();
    Ok(FinishedRun {
        trajectory: keyframes.clone(),
        keyframes,
        loops,
        model,
        coloured,
        mesh: None,
        final_optimise_ms: 0.0,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rgbid::io::run_folder::{LoopRow, RunFolderWriter, RunSummary};

    #[test]
    fn output_folder_from_the_library_writer() {
        let dir = std::env::temp_dir().join(format!("rgbid-viewer-out-{}", std::process::id()));
        let mut w = RunFolderWriter::create(&dir).unwrap();
        let pose = |t: f64| TimedPose {
            timestamp: t,
            world_from_camera: rgbid::geometry::Se3::default(),
        };
        w.frame(&FrameRow {
            index: 0,
            fusion_ms: 0.6,
            sigma_photo: Some(0.0),
            nu: Some(5.5),
            ..Default::default()
        })
        .unwrap();
        w.odometry_pose(&pose(0.0)).unwrap();
        let accepted = LoopRow {
            query: 1,
            candidate: 0,
            accepted: true,
            ..Default::default()
        };
        w.loop_checked(&accepted).unwrap();
        w.loop_checked(&LoopRow {
            query: 1,
            candidate: 0,
            relocalisation: true,
            accepted: true,
            ..Default::default()
        })
        .unwrap();
        w.keyframes(&[pose(0.0), pose(1.0)]).unwrap();
        w.trajectory(&[pose(0.0), pose(1.0)]).unwrap();
        w.model(&[(glam::DVec3::new(1.0, 2.0, 3.0), 7)]).unwrap();
        w.finish(RunSummary::default()).unwrap();
        let f = load_output(&dir).unwrap();
        assert_eq!(f.run.loops, vec![(1, 0)]);
        assert_eq!(f.run.trajectory.len(), 2);
        assert_eq!(f.run.model.len(), 1);
        assert_eq!(f.stages[0].fusion_ms, 0.6);
        assert!(known(f.stages[0].sigma_photo).is_nan());
        assert_eq!(f.stages[0].nu, Some(5.5));
        std::fs::remove_dir_all(&dir).ok();
        assert!(load_output(&dir).is_err());
    }
}
