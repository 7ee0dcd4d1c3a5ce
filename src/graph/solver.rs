//! Sparse non-linear least squares over manifold variables: Levenberg-Marquardt and
//! Gauss-Newton with robust kernels and a sparse Cholesky (faer, AMD ordering) whose symbolic
//! analysis is computed once per graph structure and reused across iterations and calls.
//!
//! The cost is `sum_k rho(|r_k|^2)` where `r_k` is the whitened residual of factor `k`
//! (`r = L^T e` with `Omega = L L^T` the information matrix) and `rho` the robust kernel
//! (identity without one), so without a kernel the cost is the usual chi2 `sum e^T Omega e`.

use std::time::Instant;

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::sparse::linalg::cholesky::{
    factorize_symbolic_cholesky, LltRef, SymbolicCholesky, SymmetricOrdering,
};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};
use faer::{Conj, Par, Side};
use rayon::prelude::*;

use super::lie::Manifold;
use super::GraphError;

/// A cost term over a few variables of a [`Problem`].
pub trait Factor<V>: Send + Sync {
    /// Indices (into the problem's variables) of the variables it depends on.
    fn variables(&self) -> &[usize];
    /// Dimension of the (whitened) residual.
    fn residual_dim(&self) -> usize;
    /// Evaluates the whitened residual `r` (length `residual_dim()`) at `values` and, when
    /// `jacobian` is given, its Jacobian with respect to the tangent increments of each of
    /// `variables()`, row-major `residual_dim() x (variables().len() * V::DIM)`.
    fn evaluate(&self, values: &[V], r: &mut [f64], jacobian: Option<&mut [f64]>);
}

/// Robust kernel `rho(s)` applied to the squared whitened residual `s = |r|^2`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum RobustKernel {
    /// `rho(s) = s` for `s <= d^2`, `2 d sqrt(s) - d^2` beyond.
    Huber(f64),
    /// `rho(s) = 2 d^2 (sqrt(1 + s / d^2) - 1)`.
    PseudoHuber(f64),
    /// `rho(s) = d^2 ln(1 + s / d^2)`.
    Cauchy(f64),
}

impl RobustKernel {
    /// `(rho(s), rho'(s))`.
    pub fn apply(&self, s: f64) -> (f64, f64) {
        match *self {
            RobustKernel::Huber(d) => {
                let d2 = d * d;
                if s <= d2 {
                    (s, 1.0)
                } else {
                    let r = s.sqrt();
                    (2.0 * d * r - d2, d / r)
                }
            }
            RobustKernel::PseudoHuber(d) => {
                let d2 = d * d;
                let q = (1.0 + s / d2).sqrt();
                (2.0 * d2 * (q - 1.0), 1.0 / q)
            }
            RobustKernel::Cauchy(d) => {
                let d2 = d * d;
                (d2 * (1.0 + s / d2).ln(), 1.0 / (1.0 + s / d2))
            }
        }
    }
}

/// Optimisation algorithm.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Algorithm {
    /// Levenberg-Marquardt with Marquardt (diagonal) damping and Nielsen's update.
    #[default]
    LevenbergMarquardt,
    /// Gauss-Newton (stops when a step does not decrease the cost).
    GaussNewton,
}

/// Solver settings.
#[derive(Clone, Debug)]
pub struct SolverOptions {
    /// LM or GN.
    pub algorithm: Algorithm,
    /// Maximum number of iterations (linear solves).
    pub max_iterations: usize,
    /// Stop when an accepted step decreases the cost by less than this fraction of it.
    pub relative_tolerance: f64,
    /// Stop when the cost is below this value.
    pub absolute_tolerance: f64,
    /// Robust kernel applied to every factor, if any.
    pub kernel: Option<RobustKernel>,
    /// Initial LM damping (relative to the Hessian diagonal).
    pub initial_lambda: f64,
    /// Log every iteration at `info` level.
    pub verbose: bool,
}

impl Default for SolverOptions {
    fn default() -> Self {
        SolverOptions {
            algorithm: Algorithm::LevenbergMarquardt,
            max_iterations: 500,
            relative_tolerance: 1e-7,
            absolute_tolerance: 1e-12,
            kernel: None,
            initial_lambda: 1e-5,
            verbose: false,
        }
    }
}

/// One iteration of the solver.
#[derive(Clone, Debug)]
pub struct IterationRecord {
    /// 1-based iteration number.
    pub iteration: usize,
    /// Cost after the iteration (of the accepted estimate).
    pub cost: f64,
    /// Damping used (0 for GN).
    pub lambda: f64,
    /// Whether the step was accepted.
    pub accepted: bool,
    /// Seconds since the start of `optimize`.
    pub seconds: f64,
}

/// Why the solver stopped.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Termination {
    /// The relative cost decrease fell below the tolerance.
    Converged,
    /// The cost fell below the absolute tolerance.
    CostBelowTolerance,
    /// No step decreases the cost any more (LM damping exhausted / GN step increased the cost).
    NoProgress,
    /// `max_iterations` reached.
    MaxIterations,
    /// Nothing to optimise (no free variables or no factors).
    Trivial,
}

/// What `optimize` did.
#[derive(Clone, Debug)]
pub struct SolveReport {
    /// Cost at the start.
    pub initial_cost: f64,
    /// Cost at the end.
    pub final_cost: f64,
    /// Number of iterations (linear solves).
    pub iterations: usize,
    /// Per-iteration history.
    pub history: Vec<IterationRecord>,
    /// Why it stopped.
    pub termination: Termination,
    /// Wall time of `optimize` in seconds.
    pub seconds: f64,
    /// Seconds spent in the symbolic analysis (0 when reused).
    pub symbolic_seconds: f64,
}

/// The cached sparsity structure of the normal equations.
struct Structure {
    dim: usize,
    var_of: Vec<usize>,
    n: usize,
    col_ptr: Vec<usize>,
    row_idx: Vec<usize>,
    /// Per factor: range into `blocks`.
    factor_block_start: Vec<usize>,
    /// (slot a, slot b, position of block row in its block column, block column).
    blocks: Vec<(u8, u8, usize, usize)>,
    diag_idx: Vec<usize>,
    symbolic: SymbolicCholesky<usize>,
    n_factors: usize,
}

const NONE: usize = usize::MAX;

/// A non-linear least-squares problem: variables of one manifold type and factors on them.
///
/// Variables can be added, fixed and changed between calls to [`Problem::optimize`]; the
/// sparsity analysis is redone only when the structure changes (an incremental back-end adds
/// vertices and factors and re-optimises from the current estimate).
pub struct Problem<V: Manifold> {
    /// Current values of the variables.
    pub values: Vec<V>,
    fixed: Vec<bool>,
    factors: Vec<Box<dyn Factor<V>>>,
    structure: Option<Structure>,
}

impl<V: Manifold> Default for Problem<V> {
    fn default() -> Self {
        Self::new()
    }
}

impl<V: Manifold> Problem<V> {
    /// An empty problem.
    pub fn new() -> Self {
        Problem {
            values: Vec::new(),
            fixed: Vec::new(),
            factors: Vec::new(),
            structure: None,
        }
    }
    /// Adds a variable with its initial value; returns its index.
    pub fn add_variable(&mut self, value: V) -> usize {
        self.values.push(value);
        self.fixed.push(false);
        self.structure = None;
        self.values.len() - 1
    }
    /// Fixes (or frees) a variable.
    pub fn set_fixed(&mut self, index: usize, fixed: bool) {
        if let Some(f) = self.fixed.get_mut(index) {
            if *f != fixed {
                *f = fixed;
                self.structure = None;
            }
        }
    }
    /// Whether a variable is fixed.
    pub fn is_fixed(&self, index: usize) -> bool {
        self.fixed.get(index).copied().unwrap_or(false)
    }
    /// Adds a factor; its variable indices must exist.
    pub fn add_factor(&mut self, factor: Box<dyn Factor<V>>) -> Result<usize, GraphError> {
        if let Some(&bad) = factor.variables().iter().find(|&&v| v >= self.values.len()) {
            return Err(GraphError::UnknownVertex(bad as i64));
        }
        if factor.variables().len() > 255 {
            return Err(GraphError::Invalid(
                "factor with more than 255 variables".into(),
            ));
        }
        self.factors.push(factor);
        self.structure = None;
        Ok(self.factors.len() - 1)
    }
    /// Number of factors.
    pub fn num_factors(&self) -> usize {
        self.factors.len()
    }
    /// The factors.
    pub fn factors(&self) -> &[Box<dyn Factor<V>>] {
        &self.factors
    }

    /// Total cost `sum rho(|r|^2)` at the current values.
    pub fn cost(&self, kernel: Option<RobustKernel>) -> f64 {
        cost_of(&self.factors, &self.values, kernel)
    }

    fn build_structure(&mut self) -> Result<f64, GraphError> {
        let t0 = Instant::now();
        let d = V::DIM;
        let mut var_of = vec![NONE; self.values.len()];
        let mut nv = 0;
        for (i, f) in self.fixed.iter().enumerate() {
            if !f {
                var_of[i] = nv;
                nv += 1;
            }
        }
        // Block pattern: for each block column, the sorted block rows (<= column).
        let mut cols: Vec<Vec<usize>> = (0..nv).map(|c| vec![c]).collect();
        for f in &self.factors {
            let vs = f.variables();
            for a in 0..vs.len() {
                for b in 0..vs.len() {
                    let (va, vb) = (var_of[vs[a]], var_of[vs[b]]);
                    if va != NONE && vb != NONE && va < vb {
                        cols[vb].push(va);
                    }
                }
            }
        }
        for c in cols.iter_mut() {
            c.sort_unstable();
            c.dedup();
        }
        let n = nv * d;
        let mut col_ptr = Vec::with_capacity(n + 1);
        let mut row_idx = Vec::new();
        col_ptr.push(0);
        let mut diag_idx = vec![0; n];
        for (bc, rows) in cols.iter().enumerate() {
            for c in 0..d {
                for &br in rows {
                    let top = if br == bc { c + 1 } else { d };
                    for r in 0..top {
                        row_idx.push(br * d + r);
                    }
                }
                diag_idx[bc * d + c] = row_idx.len() - 1;
                col_ptr.push(row_idx.len());
            }
        }
        let mut factor_block_start = Vec::with_capacity(self.factors.len() + 1);
        let mut blocks = Vec::new();
        for f in &self.factors {
            factor_block_start.push(blocks.len());
            let vs = f.variables();
            for a in 0..vs.len() {
                for b in 0..vs.len() {
                    let (va, vb) = (var_of[vs[a]], var_of[vs[b]]);
                    if va == NONE || vb == NONE || va > vb || (va == vb && a > b) {
                        continue;
                    }
                    let pos = cols[vb].binary_search(&va).unwrap_or(0);
                    blocks.push((a as u8, b as u8, pos, vb));
                }
            }
        }
        factor_block_start.push(blocks.len());
        let symbolic = {
            let sym = SymbolicSparseColMatRef::new_checked(n, n, &col_ptr, None, &row_idx);
            // faer's default threshold (1.0) keeps the simplicial factorisation on graphs such
            // as parking-garage where the supernodal one is clearly faster; 0.5 switches
            // those and leaves the other benchmark files unchanged (docs/notes.md).
            let params = faer::sparse::linalg::cholesky::CholeskySymbolicParams {
                supernodal_flop_ratio_threshold: faer::sparse::linalg::SupernodalThreshold(0.5),
                ..Default::default()
            };
            factorize_symbolic_cholesky(sym, Side::Upper, SymmetricOrdering::Amd, params)
                .map_err(|e| GraphError::Linear(format!("symbolic factorisation: {e:?}")))?
        };
        self.structure = Some(Structure {
            dim: d,
            var_of,
            n,
            col_ptr,
            row_idx,
            factor_block_start,
            blocks,
            diag_idx,
            symbolic,
            n_factors: self.factors.len(),
        });
        Ok(t0.elapsed().as_secs_f64())
    }

    /// Runs LM or GN from the current values; the values are updated in place.
    pub fn optimize(&mut self, opts: &SolverOptions) -> Result<SolveReport, GraphError> {
        let t0 = Instant::now();
        if let Some(i) = self.values.iter().position(|v| !v.is_finite()) {
            return Err(GraphError::NonFinite(format!(
                "initial value of variable {i}"
            )));
        }
        let symbolic_seconds = match &self.structure {
            Some(s) if s.n_factors == self.factors.len() && s.var_of.len() == self.values.len() => {
                0.0
            }
            _ => self.build_structure()?,
        };
        let kernel = opts.kernel;
        let initial_cost = self.cost(kernel);
        if !initial_cost.is_finite() {
            return Err(GraphError::NonFinite("initial cost".into()));
        }
        let Some(st) = self.structure.as_ref() else {
            return Err(GraphError::Linear("no structure".into()));
        };
        let mut report = SolveReport {
            initial_cost,
            final_cost: initial_cost,
            iterations: 0,
            history: Vec::new(),
            termination: Termination::Trivial,
            seconds: 0.0,
            symbolic_seconds,
        };
        if st.n == 0 || self.factors.is_empty() {
            report.seconds = t0.elapsed().as_secs_f64();
            return Ok(report);
        }
        let par = if rayon::current_num_threads() > 1 {
            Par::rayon(0)
        } else {
            Par::Seq
        };
        let mut l_values = vec![0.0; st.symbolic.len_val()];
        let mut mem = MemBuffer::new(
            st.symbolic
                .factorize_numeric_llt_scratch::<f64>(par, Default::default())
                .or(st.symbolic.solve_in_place_scratch::<f64>(1, par)),
        );
        let lm = opts.algorithm == Algorithm::LevenbergMarquardt;
        let mut lambda = if lm { opts.initial_lambda } else { 0.0 };
        let mut nu = 2.0;
        let mut cost = initial_cost;
        let (mut h, mut b) = assemble(&self.factors, &self.values, st, kernel);
        let mut termination = Termination::MaxIterations;
        let mut dx = vec![0.0; st.n];
        let mut hd = vec![0.0; st.n];
        let max_diag = st
            .diag_idx
            .iter()
            .map(|&k| h[k])
            .fold(0.0, f64::max)
            .max(1e-300);
        for it in 1..=opts.max_iterations {
            report.iterations = it;
            // Damped system (H + lambda D) dx = -b with D = diag(H) clamped from below.
            for (k, &di) in st.diag_idx.iter().enumerate() {
                let dk = h[di].max(1e-9 * max_diag);
                hd[k] = dk;
                h[di] += if lm { lambda * dk } else { 1e-12 * dk };
            }
            let factor_ok = {
                let a = SparseColMatRef::new(
                    SymbolicSparseColMatRef::new_checked(
                        st.n,
                        st.n,
                        &st.col_ptr,
                        None,
                        &st.row_idx,
                    ),
                    &h,
                );
                st.symbolic
                    .factorize_numeric_llt::<f64>(
                        &mut l_values,
                        a,
                        Side::Upper,
                        Default::default(),
                        par,
                        MemStack::new(&mut mem),
                        Default::default(),
                    )
                    .is_ok()
            };
            // Undo the damping.
            for (k, &di) in st.diag_idx.iter().enumerate() {
                h[di] -= if lm { lambda * hd[k] } else { 1e-12 * hd[k] };
            }
            if !factor_ok {
                if lm {
                    lambda *= nu;
                    nu *= 2.0;
                    report.history.push(IterationRecord {
                        iteration: it,
                        cost,
                        lambda,
                        accepted: false,
                        seconds: t0.elapsed().as_secs_f64(),
                    });
                    if lambda > 1e12 {
                        termination = Termination::NoProgress;
                        break;
                    }
                    continue;
                }
                return Err(GraphError::SingularSystem);
            }
            for (x, bi) in dx.iter_mut().zip(&b) {
                *x = -bi;
            }
            {
                let llt = LltRef::new(&st.symbolic, &l_values);
                let rhs = faer::MatMut::from_column_major_slice_mut(&mut dx, st.n, 1);
                llt.solve_in_place_with_conj(Conj::No, rhs, par, MemStack::new(&mut mem));
            }
            if dx.iter().any(|x| !x.is_finite()) {
                return Err(GraphError::NonFinite("linear solve".into()));
            }
            let new_values = retract_all(&self.values, &dx, st);
            let new_cost = cost_of(&self.factors, &new_values, kernel);
            // Predicted decrease of the cost (= 2 x the usual 1/2-scaled model).
            let mut pred = 0.0;
            for k in 0..st.n {
                pred += -dx[k] * b[k]
                    + if lm {
                        lambda * hd[k] * dx[k] * dx[k]
                    } else {
                        0.0
                    };
            }
            let actual = cost - new_cost;
            let accepted = new_cost.is_finite() && actual > 0.0;
            if accepted {
                let rho = if pred > 0.0 { actual / pred } else { 0.0 };
                self.values = new_values;
                let old = cost;
                cost = new_cost;
                if lm {
                    // Nielsen's update, allowed to shrink 10x (not 3x) per good step: on
                    // the benchmark graphs this cuts iterations by a quarter to a half with the
                    // same final chi2.
                    lambda *= f64::max(0.1, 1.0 - (2.0 * rho - 1.0).powi(3));
                    lambda = lambda.max(1e-12);
                    nu = 2.0;
                }
                report.history.push(IterationRecord {
                    iteration: it,
                    cost,
                    lambda,
                    accepted,
                    seconds: t0.elapsed().as_secs_f64(),
                });
                if opts.verbose {
                    log::info!("iter {it:3}  cost {cost:.6e}  lambda {lambda:.2e}");
                }
                if cost <= opts.absolute_tolerance {
                    termination = Termination::CostBelowTolerance;
                    break;
                }
                if actual <= opts.relative_tolerance * old {
                    termination = Termination::Converged;
                    break;
                }
                let (h2, b2) = assemble(&self.factors, &self.values, st, kernel);
                h = h2;
                b = b2;
            } else {
                report.history.push(IterationRecord {
                    iteration: it,
                    cost,
                    lambda,
                    accepted,
                    seconds: t0.elapsed().as_secs_f64(),
                });
                if opts.verbose {
                    log::info!("iter {it:3}  rejected (cost {new_cost:.6e})  lambda {lambda:.2e}");
                }
                if !lm {
                    termination = Termination::NoProgress;
                    break;
                }
                // A rejected step with a negligible predicted decrease: at a minimum.
                if pred.abs() <= opts.relative_tolerance * 1e-3 * cost {
                    termination = Termination::Converged;
                    break;
                }
                lambda *= nu;
                nu *= 2.0;
                if lambda > 1e12 {
                    termination = Termination::NoProgress;
                    break;
                }
            }
        }
        report.final_cost = cost;
        report.termination = termination;
        report.seconds = t0.elapsed().as_secs_f64();
        Ok(report)
    }
}

fn retract_all<V: Manifold>(values: &[V], dx: &[f64], st: &Structure) -> Vec<V> {
    let d = st.dim;
    values
        .par_iter()
        .enumerate()
        .map(|(i, v)| {
            let k = st.var_of[i];
            if k == NONE {
                v.clone()
            } else {
                v.retract(&dx[k * d..k * d + d])
            }
        })
        .collect()
}

fn cost_of<V: Manifold>(
    factors: &[Box<dyn Factor<V>>],
    values: &[V],
    kernel: Option<RobustKernel>,
) -> f64 {
    factors
        .par_iter()
        .with_min_len(256)
        .map_init(Vec::new, |r, f| {
            r.resize(f.residual_dim(), 0.0);
            f.evaluate(values, r, None);
            let s: f64 = r.iter().map(|x| x * x).sum();
            match kernel {
                Some(k) => k.apply(s).0,
                None => s,
            }
        })
        .sum()
}

/// Builds the upper triangle of `H = sum w J^T J` (values in the structure's order) and
/// `b = sum w J^T r`.
fn assemble<V: Manifold>(
    factors: &[Box<dyn Factor<V>>],
    values: &[V],
    st: &Structure,
    kernel: Option<RobustKernel>,
) -> (Vec<f64>, Vec<f64>) {
    let d = st.dim;
    let nnz = st.row_idx.len();
    let nchunks = (rayon::current_num_threads() * 2).max(1);
    let chunk = factors.len().div_ceil(nchunks).max(1);
    let parts: Vec<(Vec<f64>, Vec<f64>)> = factors
        .par_chunks(chunk)
        .enumerate()
        .map(|(ci, fs)| {
            let mut h = vec![0.0; nnz];
            let mut b = vec![0.0; st.n];
            let mut r = Vec::new();
            let mut j = Vec::new();
            for (fi, f) in fs.iter().enumerate() {
                let fidx = ci * chunk + fi;
                let m = f.residual_dim();
                let vs = f.variables();
                let cols = vs.len() * d;
                r.resize(m, 0.0);
                j.clear();
                j.resize(m * cols, 0.0);
                f.evaluate(values, &mut r, Some(&mut j));
                let s: f64 = r.iter().map(|x| x * x).sum();
                let w = match kernel {
                    Some(k) => k.apply(s).1,
                    None => 1.0,
                };
                for (slot, &v) in vs.iter().enumerate() {
                    let k = st.var_of[v];
                    if k == NONE {
                        continue;
                    }
                    for c in 0..d {
                        let mut acc = 0.0;
                        for row in 0..m {
                            acc += j[row * cols + slot * d + c] * r[row];
                        }
                        b[k * d + c] += w * acc;
                    }
                }
                for &(a, bb, pos, bc) in
                    &st.blocks[st.factor_block_start[fidx]..st.factor_block_start[fidx + 1]]
                {
                    let (a, bb) = (a as usize, bb as usize);
                    let diag = st.var_of[vs[a]] == bc;
                    for c in 0..d {
                        let base = st.col_ptr[bc * d + c] + pos * d;
                        let top = if diag { c + 1 } else { d };
                        for rr in 0..top {
                            let mut acc = 0.0;
                            for row in 0..m {
                                acc += j[row * cols + a * d + rr] * j[row * cols + bb * d + c];
                            }
                            h[base + rr] += w * acc;
                        }
                    }
                    // Two slots on the same variable: add the transposed block too.
                    if diag && a != bb {
                        for c in 0..d {
                            let base = st.col_ptr[bc * d + c] + pos * d;
                            for rr in 0..=c {
                                let mut acc = 0.0;
                                for row in 0..m {
                                    acc += j[row * cols + bb * d + rr] * j[row * cols + a * d + c];
                                }
                                h[base + rr] += w * acc;
                            }
                        }
                    }
                }
            }
            (h, b)
        })
        .collect();
    let mut iter = parts.into_iter();
    let (mut h, mut b) = iter
        .next()
        .unwrap_or_else(|| (vec![0.0; nnz], vec![0.0; st.n]));
    for (h2, b2) in iter {
        h.par_iter_mut()
            .zip(h2.par_iter())
            .for_each(|(x, y)| *x += y);
        for (x, y) in b.iter_mut().zip(&b2) {
            *x += y;
        }
    }
    (h, b)
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DVec2;

    /// r = (x_b - x_a - d) * sqrt(w)
    struct Diff {
        vars: [usize; 2],
        d: DVec2,
        w: f64,
    }
    impl Factor<DVec2> for Diff {
        fn variables(&self) -> &[usize] {
            &self.vars
        }
        fn residual_dim(&self) -> usize {
            2
        }
        fn evaluate(&self, v: &[DVec2], r: &mut [f64], j: Option<&mut [f64]>) {
            let e = (v[self.vars[1]] - v[self.vars[0]] - self.d) * self.w.sqrt();
            r[0] = e.x;
            r[1] = e.y;
            if let Some(j) = j {
                let s = self.w.sqrt();
                j.copy_from_slice(&[-s, 0.0, s, 0.0, 0.0, -s, 0.0, s]);
            }
        }
    }

    fn chain() -> Problem<DVec2> {
        let mut p = Problem::new();
        for i in 0..5 {
            p.add_variable(DVec2::new(i as f64 * 0.3, 1.0));
        }
        p.set_fixed(0, true);
        for i in 0..4 {
            p.add_factor(Box::new(Diff {
                vars: [i, i + 1],
                d: DVec2::new(1.0, 0.0),
                w: 1.0,
            }))
            .unwrap();
        }
        // A loop closure 0 -> 4 that disagrees slightly.
        p.add_factor(Box::new(Diff {
            vars: [0, 4],
            d: DVec2::new(4.4, 0.0),
            w: 4.0,
        }))
        .unwrap();
        p
    }

    #[test]
    fn linear_problem_solves_to_least_squares_optimum() {
        for algorithm in [Algorithm::LevenbergMarquardt, Algorithm::GaussNewton] {
            let mut p = chain();
            let rep = p
                .optimize(&SolverOptions {
                    algorithm,
                    ..Default::default()
                })
                .unwrap();
            // Optimum: 4 unit-weight steps of length a, closure weight 4: 4(a-1) = 4*(4.4-4a)
            // per step: minimise 4(a-1)^2 + 4(4a-4.4)^2 -> a = (1 + 4*4.4)/(1+16) = 18.6/17.
            let a = 18.6 / 17.0;
            for i in 0..5 {
                assert!(
                    (p.values[i].x - p.values[0].x - a * i as f64).abs() < 1e-6,
                    "{algorithm:?} {i}"
                );
                assert!((p.values[i].y - 1.0).abs() < 1e-9);
            }
            let expected = 4.0 * (a - 1.0).powi(2) + 4.0 * (4.0 * a - 4.4).powi(2);
            assert!(
                (rep.final_cost - expected).abs() < 1e-8,
                "{} vs {expected}",
                rep.final_cost
            );
        }
    }

    #[test]
    fn robust_kernels_are_consistent() {
        for k in [
            RobustKernel::Huber(1.5),
            RobustKernel::PseudoHuber(1.5),
            RobustKernel::Cauchy(1.5),
        ] {
            for s in [0.1, 1.0, 3.0, 50.0] {
                let (rho, d) = k.apply(s);
                let h = 1e-6;
                let fd = (k.apply(s + h).0 - k.apply(s - h).0) / (2.0 * h);
                assert!((fd - d).abs() < 1e-6, "{k:?} {s}");
                assert!(rho <= s + 1e-12 && d <= 1.0 + 1e-12);
            }
        }
    }

    #[test]
    fn outlier_is_downweighted_by_kernel() {
        let mut p = chain();
        p.add_factor(Box::new(Diff {
            vars: [1, 3],
            d: DVec2::new(10.0, 5.0),
            w: 1.0,
        }))
        .unwrap();
        p.optimize(&SolverOptions {
            kernel: Some(RobustKernel::Cauchy(1.0)),
            ..Default::default()
        })
        .unwrap();
        let step = p.values[3].x - p.values[1].x;
        assert!((step - 2.0 * 18.6 / 17.0).abs() < 0.1, "{step}");
        assert!((p.values[3].y - 1.0).abs() < 0.1);
    }

    #[test]
    fn bad_factor_index_is_an_error() {
        let mut p = chain();
        assert!(p
            .add_factor(Box::new(Diff {
                vars: [0, 9],
                d: DVec2::ZERO,
                w: 1.0
            }))
            .is_err());
    }
}
