//! The SLAM system's records as the plain rows of a run folder ([`crate::io::run_folder`]).

use super::{FrameRecord, KeyframeTiming, LoopRecord};
use crate::io::run_folder::{FrameRow, KeyframeTimingRow, LoopRow};

/// `v` rounded to `decimals` decimals: the files keep the precision that means something
/// (microseconds, 1e-4 of covisibility) instead of every digit of an f64.
fn round(v: f64, decimals: i32) -> f64 {
    let s = 10f64.powi(decimals);
    let r = (v * s).round() / s;
    if r.is_finite() {
        r
    } else {
        v
    }
}

impl From<&FrameRecord> for FrameRow {
    fn from(r: &FrameRecord) -> Self {
        let t = &r.times;
        let d = &r.diagnostics;
        FrameRow {
            index: r.index,
            timestamp: round(r.timestamp, 6),
            status: format!("{:?}", r.status),
            frontend_ms: round(r.frontend_ms, 3),
            pyramid_ms: round(t.pyramid_ms, 3),
            scale_ms: round(t.scale_ms, 3),
            reduce_ms: round(t.reduce_ms, 3),
            solve_ms: round(t.solve_ms, 3),
            covisibility_ms: round(t.covisibility_ms, 3),
            fusion_ms: round(r.fusion_ms, 3),
            covisibility: round(r.covisibility, 4),
            keyframe_covisibility: round(r.keyframe_covisibility, 4),
            sigma_photo: Some(round(d.sigma_photo, 4)),
            sigma_geo: Some(d.sigma_geo),
            nu: Some(round(d.nu, 3)),
            condition_number: Some(d.condition_number),
            iterations: Some(d.iterations),
        }
    }
}

impl From<&LoopRecord> for LoopRow {
    fn from(l: &LoopRecord) -> Self {
        LoopRow {
            query: l.query,
            candidate: l.candidate,
            inliers: l.inliers,
            refine_translation_m: round(l.refine_translation, 5),
            refine_rotation_rad: round(l.refine_rotation, 5),
            covisibility: round(l.covisibility, 4),
            accepted: l.verdict.is_accepted(),
            relocalisation: l.relocalisation,
            reason: l.verdict.reason().to_string(),
        }
    }
}

impl From<&KeyframeTiming> for KeyframeTimingRow {
    fn from(t: &KeyframeTiming) -> Self {
        KeyframeTimingRow {
            id: t.id,
            segment_ms: round(t.segment_ms, 3),
            describe_ms: round(t.describe_ms, 3),
            query_ms: round(t.query_ms, 3),
            align_ms: round(t.align_ms, 3),
            optimise_ms: round(t.optimise_ms, 3),
            total_ms: round(t.total_ms, 3),
        }
    }
}
