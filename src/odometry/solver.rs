//! Finishing the GPU/CPU partial sums in f64 and solving the 6x6 normal equations.

use nalgebra::{Matrix6, SymmetricEigen, Vector6};

use super::kernel::Partial;
use crate::geometry::Covariance6;

/// The IRLS normal equations of one iteration, summed in f64.
#[derive(Clone, Debug)]
pub struct NormalEquations {
    /// Gauss-Newton Hessian approximation `sum w J^T J / sigma^2`.
    pub h: Matrix6<f64>,
    /// Gradient `sum w J^T r / sigma^2`.
    pub g: Vector6<f64>,
    /// Weighted cost `sum w (r / sigma)^2`.
    pub cost: f64,
    /// Valid photometric residuals.
    pub n_photo: u64,
    /// Valid geometric residuals.
    pub n_geo: u64,
}

impl NormalEquations {
    /// Sums partials (f32 each) in f64.
    pub fn from_partials(partials: &[Partial]) -> Self {
        let (mut hs, mut gs) = ([0.0f64; 21], [0.0f64; 6]);
        let (mut cost, mut n_photo, mut n_geo) = (0.0f64, 0.0f64, 0.0f64);
        for p in partials {
            for (s, v) in hs.iter_mut().zip(&p.h) {
                *s += f64::from(*v);
            }
            for (s, v) in gs.iter_mut().zip(&p.g) {
                *s += f64::from(*v);
            }
            cost += f64::from(p.cost);
            n_photo += f64::from(p.n_photo);
            n_geo += f64::from(p.n_geo);
        }
        let mut h = Matrix6::zeros();
        let mut k = 0;
        for a in 0..6 {
            for b in a..6 {
                h[(a, b)] = hs[k];
                h[(b, a)] = hs[k];
                k += 1;
            }
        }
        Self {
            h,
            g: Vector6::from_column_slice(&gs),
            cost,
            n_photo: n_photo.round() as u64,
            n_geo: n_geo.round() as u64,
        }
    }

    /// Solves `H delta = -g`; `None` if H is not positive definite.
    pub fn solve(&self) -> Option<[f64; 6]> {
        let chol = self.h.cholesky()?;
        let d = chol.solve(&(-self.g));
        d.iter()
            .all(|x| x.is_finite())
            .then(|| [d[0], d[1], d[2], d[3], d[4], d[5]])
    }

    /// Inverse of H (the estimate's covariance, twist order `[v; w]`) and the condition
    /// number of H.
    pub fn covariance(&self) -> Option<(Covariance6, f64)> {
        let eig = SymmetricEigen::new(self.h);
        let max = eig.eigenvalues.max();
        let min = eig.eigenvalues.min();
        if !(min > 0.0) {
            return None;
        }
        let inv = self.h.cholesky()?.inverse();
        let mut c = [[0.0; 6]; 6];
        for (a, row) in c.iter_mut().enumerate() {
            for (b, v) in row.iter_mut().enumerate() {
                *v = inv[(a, b)];
            }
        }
        Some((Covariance6::from_rows(c), max / min))
    }
}
