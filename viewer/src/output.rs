//! Reading what `rgbid slam` wrote (trajectory.txt, groundtruth.txt, keyframes.txt, loops.csv,
//! timing.csv, model.ply) and saved maps, for display.

use std::path::Path;

use anyhow::{bail, Context, Result};
use glam::DVec3;
use rgbid::io::trajectory::read_tum;
use rgbid::slam::{build_model, voxel_filter, Map, ModelParams};
use rgbid::trajectory::TimedPose;

use crate::worker::FinishedRun;

/// One row of per-frame statistics (live from `FrameReport`s or from timing.csv).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StageRow {
    /// Frame index.
    pub index: usize,
    /// Front-end total, ms.
    pub frontend_ms: f64,
    /// Pyramid construction, ms.
    pub pyramid_ms: f64,
    /// Robust scale estimation, ms.
    pub scale_ms: f64,
    /// Residuals + normal-equation reduction, ms.
    pub reduce_ms: f64,
    /// 6x6 solves, ms.
    pub solve_ms: f64,
    /// Covisibility, ms.
    pub covisibility_ms: f64,
    /// Keyframe fusion, ms.
    pub fusion_ms: f64,
    /// Covisibility with the odometry reference.
    pub covisibility: f64,
    /// Covisibility of the keyframe with the frame.
    pub keyframe_covisibility: f64,
    /// Photometric residual scale sigma_I at the finest level, intensity levels (NaN when
    /// unknown: lost frames, older timing files).
    pub sigma_photo: f64,
    /// Geometric residual scale sigma_W at the finest level, 1/m (NaN when unknown).
    pub sigma_geo: f64,
    /// Student-t degrees of freedom (NaN when unknown).
    pub nu: f64,
    /// Condition number of the final Hessian (NaN when unknown).
    pub condition_number: f64,
}

impl StageRow {
    /// The row of a live frame record.
    pub fn from_record(r: &rgbid::slam::FrameRecord) -> Self {
        StageRow {
            index: r.index,
            frontend_ms: r.frontend_ms,
            pyramid_ms: r.times.pyramid_ms,
            scale_ms: r.times.scale_ms,
            reduce_ms: r.times.reduce_ms,
            solve_ms: r.times.solve_ms,
            covisibility_ms: r.times.covisibility_ms,
            fusion_ms: r.fusion_ms,
            covisibility: r.covisibility,
            keyframe_covisibility: r.keyframe_covisibility,
            sigma_photo: known(r.diagnostics.sigma_photo),
            sigma_geo: known(r.diagnostics.sigma_geo),
            nu: known(r.diagnostics.nu),
            condition_number: known(r.diagnostics.condition_number),
        }
    }
}

/// A diagnostic value, NaN where the front-end did not fill it (0 on lost frames).
fn known(v: f64) -> f64 {
    if v > 0.0 && v.is_finite() {
        v
    } else {
        f64::NAN
    }
}

/// Parses timing.csv as written by `rgbid slam` (header line, then one line per frame; the
/// diagnostic columns sigma_photo, sigma_geo, nu and condition_number are optional).
pub fn parse_timing_csv(text: &str) -> Result<Vec<StageRow>> {
    let mut rows = Vec::new();
    for (n, line) in text.lines().enumerate().skip(1) {
        if line.trim().is_empty() {
            continue;
        }
        let f: Vec<&str> = line.split(',').collect();
        if f.len() < 12 {
            bail!("timing.csv line {}: {} fields, expected 12", n + 1, f.len());
        }
        let num = |k: usize| -> Result<f64> {
            f[k].trim()
                .parse::<f64>()
                .with_context(|| format!("timing.csv line {} field {}", n + 1, k + 1))
        };
        rows.push(StageRow {
            index: f[0]
                .trim()
                .parse()
                .with_context(|| format!("timing.csv line {}", n + 1))?,
            frontend_ms: num(3)?,
            pyramid_ms: num(4)?,
            scale_ms: num(5)?,
            reduce_ms: num(6)?,
            solve_ms: num(7)?,
            covisibility_ms: num(8)?,
            fusion_ms: num(9)?,
            covisibility: num(10)?,
            keyframe_covisibility: num(11)?,
            sigma_photo: if f.len() > 12 {
                known(num(12)?)
            } else {
                f64::NAN
            },
            sigma_geo: if f.len() > 13 {
                known(num(13)?)
            } else {
                f64::NAN
            },
            nu: if f.len() > 14 {
                known(num(14)?)
            } else {
                f64::NAN
            },
            condition_number: if f.len() > 15 {
                known(num(15)?)
            } else {
                f64::NAN
            },
        });
    }
    Ok(rows)
}

/// Parses loops.csv: accepted, non-relocalisation loops as (query, candidate) keyframe ids.
pub fn parse_loops_csv(text: &str) -> Result<Vec<(usize, usize)>> {
    let mut out = Vec::new();
    for (n, line) in text.lines().enumerate().skip(1) {
        let f: Vec<&str> = line.split(',').collect();
        if f.len() < 8 {
            continue;
        }
        let id = |k: usize| -> Result<usize> {
            f[k].trim()
                .parse()
                .with_context(|| format!("loops.csv line {}", n + 1))
        };
        if f[6].trim() == "true" && f[7].trim() != "true" {
            out.push((id(0)?, id(1)?));
        }
    }
    Ok(out)
}

/// Reads a PLY point cloud: binary little-endian or ASCII, vertex properties x y z as float
/// and optionally red green blue as uchar (what `rgbid slam` writes). Returns world points
/// with a grey value.
pub fn read_ply(path: &Path) -> Result<Vec<(DVec3, u8)>> {
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    parse_ply(&bytes).with_context(|| format!("parsing {}", path.display()))
}

/// See [`read_ply`].
pub fn parse_ply(bytes: &[u8]) -> Result<Vec<(DVec3, u8)>> {
    const END: &[u8] = b"end_header\n";
    let Some(end) = bytes.windows(END.len()).position(|w| w == END) else {
        bail!("no end_header line");
    };
    let header = std::str::from_utf8(&bytes[..end]).context("header is not UTF-8")?;
    let body = &bytes[end + END.len()..];
    let mut lines = header.lines();
    if lines.next().map(str::trim) != Some("ply") {
        bail!("not a PLY file");
    }
    let mut binary = false;
    let mut count = None;
    let mut props: Vec<(String, String)> = Vec::new();
    let mut in_vertex = false;
    for l in lines {
        let w: Vec<&str> = l.split_whitespace().collect();
        match w.as_slice() {
            ["format", "binary_little_endian", _] => binary = true,
            ["format", "ascii", _] => binary = false,
            ["format", f, ..] => bail!("unsupported PLY format {f}"),
            ["element", "vertex", n] => {
                count = Some(n.parse::<usize>().context("vertex count")?);
                in_vertex = true;
            }
            ["element", ..] => in_vertex = false,
            ["property", ty, name] if in_vertex => props.push((ty.to_string(), name.to_string())),
            _ => {}
        }
    }
    let Some(count) = count else {
        bail!("no vertex element");
    };
    let size_of = |t: &str| -> Result<usize> {
        Ok(match t {
            "float" | "float32" | "int" | "uint" | "int32" | "uint32" => 4,
            "double" | "float64" => 8,
            "uchar" | "uint8" | "char" | "int8" => 1,
            "short" | "ushort" | "int16" | "uint16" => 2,
            _ => bail!("unsupported property type {t}"),
        })
    };
    let find = |n: &str| props.iter().position(|(_, name)| name == n);
    let (Some(ix), Some(iy), Some(iz)) = (find("x"), find("y"), find("z")) else {
        bail!("vertex needs x, y and z");
    };
    let ir = find("red");
    let mut out = Vec::with_capacity(count.min(50_000_000));
    if binary {
        let mut offsets = Vec::with_capacity(props.len());
        let mut stride = 0;
        for (t, _) in &props {
            offsets.push(stride);
            stride += size_of(t)?;
        }
        if body.len() < count.saturating_mul(stride) {
            bail!(
                "file ends early: {count} vertices of {stride} bytes need {} bytes, {} present",
                count * stride,
                body.len()
            );
        }
        let read = |rec: &[u8], k: usize| -> f64 {
            let o = offsets[k];
            match props[k].0.as_str() {
                "double" | "float64" => {
                    let mut b = [0u8; 8];
                    b.copy_from_slice(&rec[o..o + 8]);
                    f64::from_le_bytes(b)
                }
                "uchar" | "uint8" => f64::from(rec[o]),
                _ => {
                    let mut b = [0u8; 4];
                    b.copy_from_slice(&rec[o..o + 4]);
                    f64::from(f32::from_le_bytes(b))
                }
            }
        };
        for rec in body.chunks_exact(stride.max(1)).take(count) {
            let p = DVec3::new(read(rec, ix), read(rec, iy), read(rec, iz));
            let g = ir.map_or(200.0, |k| read(rec, k)).clamp(0.0, 255.0) as u8;
            out.push((p, g));
        }
    } else {
        let text = std::str::from_utf8(body).context("ASCII body is not UTF-8")?;
        for (n, line) in text.lines().take(count).enumerate() {
            let v: Vec<f64> = line
                .split_whitespace()
                .map(|s| s.parse::<f64>())
                .collect::<Result<_, _>>()
                .with_context(|| format!("vertex {n}"))?;
            if v.len() < props.len() {
                bail!("vertex {n}: {} values, expected {}", v.len(), props.len());
            }
            let g = ir.map_or(200.0, |k| v[k]).clamp(0.0, 255.0) as u8;
            out.push((DVec3::new(v[ix], v[iy], v[iz]), g));
        }
        if out.len() < count {
            bail!("file ends early: {} of {count} vertices", out.len());
        }
    }
    Ok(out)
}

/// Everything shown from a finished output folder.
#[derive(Clone, Debug, Default)]
pub struct OutputFolder {
    /// Trajectory, keyframes, loops, model.
    pub run: FinishedRun,
    /// Ground truth, if groundtruth.txt exists.
    pub groundtruth: Option<Vec<TimedPose>>,
    /// Per-frame statistics, if timing.csv exists.
    pub stages: Vec<StageRow>,
}

/// Loads an output folder of `rgbid slam`. trajectory.txt is required, the rest optional.
pub fn load_output(dir: &Path) -> Result<OutputFolder> {
    let trajectory = read_tum(&dir.join("trajectory.txt"))
        .with_context(|| format!("{} is not an rgbid slam output folder", dir.display()))?;
    let opt = |name: &str| -> Result<Option<Vec<TimedPose>>> {
        let p = dir.join(name);
        if p.exists() {
            Ok(Some(read_tum(&p)?))
        } else {
            Ok(None)
        }
    };
    let keyframes = opt("keyframes.txt")?.unwrap_or_default();
    let groundtruth = opt("groundtruth.txt")?;
    let text = |name: &str| std::fs::read_to_string(dir.join(name)).ok();
    let loops = match text("loops.csv") {
        Some(t) => parse_loops_csv(&t)?
            .into_iter()
            .filter(|(a, b)| *a < keyframes.len() && *b < keyframes.len())
            .collect(),
        None => Vec::new(),
    };
    let stages = match text("timing.csv") {
        Some(t) => parse_timing_csv(&t)?,
        None => Vec::new(),
    };
    let ply = dir.join("model.ply");
    let model = if ply.exists() {
        read_ply(&ply)?
    } else {
        Vec::new()
    };
    Ok(OutputFolder {
        run: FinishedRun {
            trajectory,
            keyframes,
            loops,
            model,
            final_optimise_ms: 0.0,
        },
        groundtruth,
        stages,
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
    let model = build_model(&map.keyframes, &poses, &map.camera, &ModelParams::default());
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
        model: voxel_filter(&model, voxel),
        final_optimise_ms: 0.0,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ply_round_trip_with_the_library_writer() {
        let dir = std::env::temp_dir().join(format!("rgbid-viewer-ply-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("m.ply");
        let pts = vec![
            (DVec3::new(1.0, -2.0, 3.5), 7u8),
            (DVec3::new(0.25, 0.5, 0.75), 200),
        ];
        rgbid::slam::write_ply(&p, &pts).unwrap();
        let back = read_ply(&p).unwrap();
        assert_eq!(back, pts);
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn ply_errors_instead_of_panics() {
        assert!(parse_ply(b"").is_err());
        assert!(parse_ply(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nend_header\n\0\0").is_err());
        assert!(parse_ply(
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n"
        )
        .is_err());
        let ok = parse_ply(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 2 3\n").unwrap();
        assert_eq!(ok, vec![(DVec3::new(1.0, 2.0, 3.0), 200)]);
    }

    #[test]
    fn timing_and_loops_csv() {
        let t = "index,timestamp,status,frontend_ms,pyramid_ms,scale_ms,reduce_ms,solve_ms,covisibility_ms,fusion_ms,covisibility,keyframe_covisibility\n\
                 0,0.000000,NewKeyframe,1.0,0.1,0.2,0.3,0.4,0.5,0.6,1.0000,1.0000\n";
        let rows = parse_timing_csv(t).unwrap();
        assert_eq!(rows.len(), 1);
        assert_eq!(rows[0].fusion_ms, 0.6);
        assert!(rows[0].sigma_photo.is_nan());
        let t2 = "h\n3,0.1,Tracking,1,0.1,0.2,0.3,0.4,0.5,0.6,0.9,0.8,4.5,0.002,5.5,1200,14\n";
        let rows = parse_timing_csv(t2).unwrap();
        assert_eq!(
            (rows[0].sigma_photo, rows[0].nu, rows[0].condition_number),
            (4.5, 5.5, 1200.0)
        );
        assert!(parse_timing_csv("h\n1,2,3\n").is_err());
        let l = "query,candidate,inliers,a,b,c,accepted,relocalisation,reason\n9,2,40,0.01,0.01,0.8,true,false,\"ok\"\n9,3,40,0.01,0.01,0.8,false,false,\"x\"\n";
        assert_eq!(parse_loops_csv(l).unwrap(), vec![(9, 2)]);
    }
}
