//! [`Covariance6`]: the covariance of a 6-DoF pose in the library's perturbation convention.

use std::ops::Add;

use nalgebra::{Matrix6, SymmetricEigen};

use super::Se3;

/// The covariance of a pose `a_from_b` as the library perturbs it (see [`crate::geometry`]):
/// the covariance of the twist `d = [v; w]` in `a_from_b * exp(d)`, expressed in frame `b`.
/// Rows and columns are ordered `v_x, v_y, v_z, w_x, w_y, w_z`; entries are in m^2 (the
/// translation block), m rad (the cross blocks) and rad^2 (the rotation block).
///
/// Used by the odometry's results, the SLAM keyframe links and, through
/// [`Covariance6::information`], the SE(3) pose-graph edges.
///
/// ```
/// use rgbid::geometry::{Covariance6, Se3};
/// let c = Covariance6::from_sigmas(0.01, 0.002); // 1 cm, 2 mrad
/// // Moving the perturbation from frame b to frame c by c_from_b keeps it positive definite.
/// let b_from_c = Se3::exp(&[0.1, 0.0, 0.0, 0.0, 0.0, 0.3]);
/// let moved = c.transported(&b_from_c);
/// assert!(moved.information().is_some());
/// assert!((c.condition_number() - 25.0).abs() < 1e-9);
/// ```
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Covariance6 {
    rows: [[f64; 6]; 6],
}

impl Covariance6 {
    /// The zero covariance (a perfectly known pose; it has no information matrix).
    pub const ZERO: Covariance6 = Covariance6 {
        rows: [[0.0; 6]; 6],
    };

    /// From a row-major 6x6 matrix (see the type's docs for the order and units). The matrix
    /// is taken as given; [`Self::information`] says whether it is positive definite.
    pub fn from_rows(rows: [[f64; 6]; 6]) -> Self {
        Covariance6 { rows }
    }

    /// A diagonal covariance: `variances` in the order `v_x .. w_z` (m^2, rad^2).
    pub fn from_diagonal(variances: [f64; 6]) -> Self {
        let mut rows = [[0.0; 6]; 6];
        for (i, v) in variances.into_iter().enumerate() {
            rows[i][i] = v;
        }
        Covariance6 { rows }
    }

    /// An isotropic covariance: standard deviation `sigma_t` (m) on each translation axis and
    /// `sigma_r` (rad) on each rotation axis.
    pub fn from_sigmas(sigma_t: f64, sigma_r: f64) -> Self {
        let (t, r) = (sigma_t * sigma_t, sigma_r * sigma_r);
        Self::from_diagonal([t, t, t, r, r, r])
    }

    /// The row-major matrix.
    pub fn rows(&self) -> &[[f64; 6]; 6] {
        &self.rows
    }

    /// True when every entry is 0.
    pub fn is_zero(&self) -> bool {
        self.rows.iter().flatten().all(|v| *v == 0.0)
    }

    /// True when every entry is finite.
    pub fn is_finite(&self) -> bool {
        self.rows.iter().flatten().all(|v| v.is_finite())
    }

    /// The covariance of the same uncertainty perturbing `x_from_c = x_from_b * b_from_c`
    /// instead of `x_from_b`: `x_from_b exp(d) b_from_c = x_from_c exp(Ad(c_from_b) d)`, so
    /// the result is `Ad(c_from_b) C Ad(c_from_b)^T`.
    pub fn transported(&self, b_from_c: &Se3) -> Self {
        let ad = b_from_c.inverse().adjoint();
        let c = &self.rows;
        let mut t = [[0.0; 6]; 6];
        for i in 0..6 {
            for j in 0..6 {
                t[i][j] = (0..6).map(|k| ad[i][k] * c[k][j]).sum();
            }
        }
        let mut out = [[0.0; 6]; 6];
        for i in 0..6 {
            for j in 0..6 {
                out[i][j] = (0..6).map(|k| t[i][k] * ad[j][k]).sum();
            }
        }
        Covariance6 { rows: out }
    }

    fn matrix(&self) -> Matrix6<f64> {
        Matrix6::from_fn(|i, j| 0.5 * (self.rows[i][j] + self.rows[j][i]))
    }

    /// The information matrix (the inverse of the symmetrised covariance), row-major; `None`
    /// when the covariance is not finite or not positive definite.
    pub fn information(&self) -> Option<[[f64; 6]; 6]> {
        if !self.is_finite() {
            return None;
        }
        let inv = self.matrix().cholesky()?.inverse();
        let mut out = [[0.0; 6]; 6];
        for (i, row) in out.iter_mut().enumerate() {
            for (j, v) in row.iter_mut().enumerate() {
                *v = inv[(i, j)];
            }
        }
        out.iter().flatten().all(|v| v.is_finite()).then_some(out)
    }

    /// Ratio of the largest to the smallest eigenvalue of the symmetrised covariance;
    /// infinite when it is singular or not finite.
    pub fn condition_number(&self) -> f64 {
        if !self.is_finite() {
            return f64::INFINITY;
        }
        let eig = SymmetricEigen::new(self.matrix());
        let (max, min) = (eig.eigenvalues.max(), eig.eigenvalues.min());
        if min > 0.0 {
            max / min
        } else {
            f64::INFINITY
        }
    }
}

impl Add for Covariance6 {
    type Output = Covariance6;
    /// The covariance of the sum of two independent perturbations in the same frame.
    fn add(self, rhs: Covariance6) -> Covariance6 {
        let mut rows = self.rows;
        for (r, o) in rows.iter_mut().zip(&rhs.rows) {
            for (a, b) in r.iter_mut().zip(o) {
                *a += b;
            }
        }
        Covariance6 { rows }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn information_inverts_and_rejects_singular_matrices() {
        let c = Covariance6::from_diagonal([1.0, 4.0, 9.0, 0.25, 0.5, 2.0]);
        let info = c.information().expect("positive definite");
        assert!((info[1][1] - 0.25).abs() < 1e-12 && (info[3][3] - 4.0).abs() < 1e-12);
        assert!(Covariance6::ZERO.information().is_none());
        let mut nan = c;
        nan.rows[2][2] = f64::NAN;
        assert!(nan.information().is_none());
        assert_eq!(nan.condition_number(), f64::INFINITY);
        assert!((c.condition_number() - 36.0).abs() < 1e-9);
    }

    #[test]
    fn transport_composes_and_sums_add() {
        let c = Covariance6::from_diagonal([1e-4, 2e-4, 3e-4, 1e-5, 2e-5, 3e-5]);
        let b_from_c = Se3::exp(&[0.2, -0.1, 0.05, 0.1, 0.3, -0.2]);
        let c_from_d = Se3::exp(&[-0.1, 0.4, 0.2, -0.2, 0.1, 0.05]);
        let twice = c.transported(&b_from_c).transported(&c_from_d);
        let once = c.transported(&(b_from_c * c_from_d));
        for i in 0..6 {
            for j in 0..6 {
                assert!((twice.rows[i][j] - once.rows[i][j]).abs() < 1e-15);
            }
        }
        assert_eq!((c + c).rows[0][0], 2e-4);
        assert_eq!(c.transported(&Se3::IDENTITY), c);
    }
}
