//! Rigid 3D-3D registration: Horn's closed-form absolute orientation (unit quaternions,
//! J. Opt. Soc. Am. A 1987) and a 3-point RANSAC around it.

use glam::{DQuat, DVec3};
use nalgebra::{Matrix4, SymmetricEigen};
use rand::{Rng, SeedableRng};

use super::PlaceError;
use crate::geometry::Se3;

/// The rigid transform `a_from_b` minimising `sum |a_i - a_from_b * b_i|^2` (Horn's method).
///
/// Needs at least 3 non-collinear pairs; points in metres.
pub fn horn_absolute_orientation(a: &[DVec3], b: &[DVec3]) -> Result<Se3, PlaceError> {
    if a.len() != b.len() {
        return Err(PlaceError::BadPointSets(format!(
            "{} vs {} points",
            a.len(),
            b.len()
        )));
    }
    if a.len() < 3 {
        return Err(PlaceError::BadPointSets(format!(
            "{} points, need at least 3",
            a.len()
        )));
    }
    let n = a.len() as f64;
    let ca = a.iter().copied().sum::<DVec3>() / n;
    let cb = b.iter().copied().sum::<DVec3>() / n;
    // Cross-covariance S = sum (b - cb)(a - ca)^T, rotation maps b onto a.
    let mut s = [[0.0f64; 3]; 3];
    let mut spread_b = 0.0;
    for (pa, pb) in a.iter().zip(b.iter()) {
        let (qa, qb) = (*pa - ca, *pb - cb);
        spread_b += qb.length_squared();
        for i in 0..3 {
            for j in 0..3 {
                s[i][j] += qb[i] * qa[j];
            }
        }
    }
    if spread_b.is_nan() || spread_b <= 1e-18 {
        return Err(PlaceError::Degenerate("all points coincide"));
    }
    let (sxx, sxy, sxz) = (s[0][0], s[0][1], s[0][2]);
    let (syx, syy, syz) = (s[1][0], s[1][1], s[1][2]);
    let (szx, szy, szz) = (s[2][0], s[2][1], s[2][2]);
    #[rustfmt::skip]
    let nmat = Matrix4::new(
        sxx + syy + szz, syz - szy,        szx - sxz,        sxy - syx,
        syz - szy,       sxx - syy - szz,  sxy + syx,        szx + sxz,
        szx - sxz,       sxy + syx,        -sxx + syy - szz, syz + szy,
        sxy - syx,       szx + sxz,        syz + szy,        -sxx - syy + szz,
    );
    if !nmat.iter().all(|v| v.is_finite()) {
        return Err(PlaceError::Degenerate("non-finite points"));
    }
    let eig = SymmetricEigen::new(nmat);
    let mut order: Vec<usize> = (0..4).collect();
    order.sort_by(|&i, &j| eig.eigenvalues[j].total_cmp(&eig.eigenvalues[i]));
    // Collinear points leave the top eigenvalue (near-)double: rotation about the line is free.
    let scale = eig
        .eigenvalues
        .iter()
        .map(|v| v.abs())
        .fold(0.0, f64::max)
        .max(1e-300);
    if (eig.eigenvalues[order[0]] - eig.eigenvalues[order[1]]) < 1e-9 * scale {
        return Err(PlaceError::Degenerate(
            "collinear points: rotation about their line is free",
        ));
    }
    let v = eig.eigenvectors.column(order[0]);
    let q = DQuat::from_xyzw(v[1], v[2], v[3], v[0]).normalize();
    let t = ca - q * cb;
    Ok(Se3::new(q, t))
}

/// RANSAC parameters.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RansacParams {
    /// Inlier threshold on the 3D residual `|a - a_from_b * b|`, metres, at 1 m depth; it grows
    /// linearly with the depth of `a` (depth noise of RGB-D sensors grows at least linearly).
    pub threshold: f64,
    /// Largest number of hypotheses.
    pub max_iterations: usize,
    /// Stop once the probability of having drawn an all-inlier sample reaches this.
    pub confidence: f64,
    /// Random seed (results are deterministic for a seed).
    pub seed: u64,
}

impl Default for RansacParams {
    fn default() -> Self {
        Self {
            threshold: 0.03,
            max_iterations: 500,
            confidence: 0.999,
            seed: 0x5eed,
        }
    }
}

/// The result of [`ransac_rigid`].
#[derive(Clone, Debug, PartialEq)]
pub struct RansacResult {
    /// The transform refitted to all inliers.
    pub a_from_b: Se3,
    /// Indices of the inlier pairs, ascending.
    pub inliers: Vec<usize>,
    /// Number of hypotheses tried.
    pub iterations: usize,
}

fn inliers_of(a: &[DVec3], b: &[DVec3], a_from_b: &Se3, threshold: f64) -> Vec<usize> {
    (0..a.len())
        .filter(|&i| {
            let tol = threshold * a[i].z.abs().max(1.0);
            (a[i] - a_from_b.transform_point(b[i])).length_squared() < tol * tol
        })
        .collect()
}

/// 3-point RANSAC for the rigid transform `a_from_b` between paired 3D points, with Horn's
/// method for each minimal sample and a final least-squares refit on the inliers (repeated
/// while the inlier set grows).
pub fn ransac_rigid(
    a: &[DVec3],
    b: &[DVec3],
    params: &RansacParams,
) -> Result<RansacResult, PlaceError> {
    if a.len() != b.len() {
        return Err(PlaceError::BadPointSets(format!(
            "{} vs {} points",
            a.len(),
            b.len()
        )));
    }
    let n = a.len();
    if n < 3 {
        return Err(PlaceError::BadPointSets(format!(
            "{n} pairs, need at least 3"
        )));
    }
    let mut rng = rand_pcg::Pcg64::seed_from_u64(params.seed);
    let mut best: Vec<usize> = Vec::new();
    let mut needed = params.max_iterations;
    let mut it = 0;
    while it < needed.min(params.max_iterations) {
        it += 1;
        let i = rng.random_range(0..n);
        let mut j = rng.random_range(0..n - 1);
        if j >= i {
            j += 1;
        }
        let mut k = rng.random_range(0..n - 2);
        for m in [i.min(j), i.max(j)] {
            if k >= m {
                k += 1;
            }
        }
        let Ok(h) = horn_absolute_orientation(&[a[i], a[j], a[k]], &[b[i], b[j], b[k]]) else {
            continue;
        };
        let inl = inliers_of(a, b, &h, params.threshold);
        if inl.len() > best.len() {
            best = inl;
            let w = best.len() as f64 / n as f64;
            let p_fail = 1.0 - w.powi(3);
            if p_fail <= 1e-12 {
                needed = it;
            } else {
                let k = ((1.0 - params.confidence).ln() / p_fail.ln()).ceil();
                if k.is_finite() && k >= 0.0 {
                    needed = (k as usize).max(1);
                }
            }
        }
    }
    if best.len() < 3 {
        return Err(PlaceError::Degenerate("no non-degenerate 3-point sample"));
    }
    let mut a_from_b = fit(a, b, &best)?;
    for _ in 0..5 {
        let inl = inliers_of(a, b, &a_from_b, params.threshold);
        if inl.len() < 3 || inl == best {
            break;
        }
        let refit = fit(a, b, &inl)?;
        if inl.len() < best.len() {
            break;
        }
        best = inl;
        a_from_b = refit;
    }
    Ok(RansacResult {
        a_from_b,
        inliers: best,
        iterations: it,
    })
}

fn fit(a: &[DVec3], b: &[DVec3], idx: &[usize]) -> Result<Se3, PlaceError> {
    let pa: Vec<DVec3> = idx.iter().map(|&i| a[i]).collect();
    let pb: Vec<DVec3> = idx.iter().map(|&i| b[i]).collect();
    horn_absolute_orientation(&pa, &pb)
}
