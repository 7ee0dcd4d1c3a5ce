//! Trajectory accuracy of graph solutions: position RMSE after rigid alignment.

use glam::{DMat3, DVec3};

use super::lie::project_to_so3;
use super::GraphError;

/// RMSE (metres) between corresponding positions after the least-squares rigid alignment of
/// `est` onto `gt` (Horn/Umeyama without scale). Errors when lengths differ or are empty.
pub fn position_rmse(est: &[DVec3], gt: &[DVec3]) -> Result<f64, GraphError> {
    if est.len() != gt.len() || est.is_empty() {
        return Err(GraphError::Invalid(format!(
            "position counts differ or are zero: {} vs {}",
            est.len(),
            gt.len()
        )));
    }
    let n = est.len() as f64;
    let ce = est.iter().copied().sum::<DVec3>() / n;
    let cg = gt.iter().copied().sum::<DVec3>() / n;
    // Cross-covariance sum (g - cg)(e - ce)^T; R = argmax tr(R^T C).
    let mut c = DMat3::ZERO;
    for (e, g) in est.iter().zip(gt) {
        let (a, b) = (*g - cg, *e - ce);
        c += DMat3::from_cols(a * b.x, a * b.y, a * b.z);
    }
    let r = project_to_so3(c);
    let s: f64 = est
        .iter()
        .zip(gt)
        .map(|(e, g)| (r * (*e - ce) + cg - *g).length_squared())
        .sum();
    Ok((s / n).sqrt())
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DQuat;

    #[test]
    fn alignment_removes_rigid_motion() {
        let gt: Vec<DVec3> = (0..20)
            .map(|i| DVec3::new(i as f64, (i as f64 * 0.3).sin(), 0.1 * i as f64))
            .collect();
        let q = DQuat::from_euler(glam::EulerRot::XYZ, 0.3, -0.2, 1.0);
        let est: Vec<DVec3> = gt
            .iter()
            .map(|p| q * *p + DVec3::new(1.0, 2.0, 3.0))
            .collect();
        assert!(position_rmse(&est, &gt).unwrap() < 1e-9);
        let mut noisy = est.clone();
        noisy[3].x += 1.0;
        let r = position_rmse(&noisy, &gt).unwrap();
        assert!(r > 0.1 && r < 1.0, "{r}");
        assert!(position_rmse(&est[..3], &gt).is_err());
    }
}
