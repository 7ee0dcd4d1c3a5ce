//! Curve-graph optimisation (thesis 7.4): the trajectory as a curve of positions only.
//!
//! Orientation is not a variable: the frame of node `c` is built from its position and the
//! positions of the previous nodes along the chain (2D: `x` along `p_c - p_{c-1}`; 3D: `x`
//! along `p_c - p_{c-1}`, `z` normal to the plane of `p_{c-2}, p_{c-1}, p_c`). The constant
//! rotation `Phi_c` between that curve frame and the pose frame is taken from the initial
//! poses, so every relative-pose edge `a -> b` becomes a constraint on the positions of `b`
//! (and of its predecessors, which carry the relative orientation) expressed in the frame of
//! `a`: ternary in 2D / quaternary in 3D for odometry, larger for loop closures. The first
//! one (2D) or two (3D) nodes plus the start node are fixed (gauge).
//!
//! Graph reduction (7.4.5) drops chain nodes closer than `th_d` metres and `th_theta` radians
//! to the last kept node (nodes in loop edges are always kept); dropped nodes are mapped back
//! rigidly to their previous kept node. After optimisation, full poses are recovered as
//! `R_c = C_c Phi_c`, `t_c = p_c`.
//!
//! Jacobians of the curve constraints are analytic (derivatives of the normalisations and cross
//! products of the frame construction), checked against central finite differences in the tests.
//!
//! Assumption: vertex order is the trajectory order, and consecutive vertices are linked by
//! an odometry edge (as in every benchmark file).

use glam::{DMat3, DVec2, DVec3};

use super::lie::{spd_inverse, Manifold, Se2};
use super::pose_graph::{Pose, PoseGraph};
use super::solver::{Factor, Problem, SolveReport, SolverOptions};
use super::GraphError;
use crate::geometry::Se3;

/// Settings of the curve-graph construction.
#[derive(Clone, Debug)]
pub struct CurveOptions {
    /// Reduction: minimal travelled distance (metres) between kept nodes (0 keeps all).
    pub th_d: f64,
    /// Reduction: minimal rotation (radians) between kept nodes.
    pub th_theta: f64,
    /// Minimal segment length (metres); shorter segments make a frame degenerate.
    pub min_segment: f64,
}

impl Default for CurveOptions {
    fn default() -> Self {
        CurveOptions {
            th_d: 0.0,
            th_theta: 0.0,
            min_segment: 1e-6,
        }
    }
}

/// A position type the curve graph runs on (`DVec2` or `DVec3`), with its pose type.
pub trait CurveSpace: Manifold + Copy + Send + Sync {
    /// The full pose type (SE(2) or SE(3)).
    type P: Pose;
    /// Number of previous nodes a frame needs (1 in 2D, 2 in 3D).
    const HISTORY: usize;
    /// Position of a pose.
    fn position_of(p: &Self::P) -> Self;
    /// Coordinates of `q` in the curve frame at `pts.last()` built from `pts` (len HISTORY+1),
    /// or `None` when the frame is degenerate.
    fn local(pts: &[Self], q: Self, min_seg: f64) -> Option<Self>;
    /// Rotation part of a pose as a matrix acting on this space (2D: 2x2 in a DMat3 corner).
    fn rotation_of(p: &Self::P) -> DMat3;
    /// Curve frame rotation (columns = axes) from `pts`.
    fn frame(pts: &[Self], min_seg: f64) -> Option<DMat3>;
    /// [`CurveSpace::local`] with its Jacobians: `out[k]` is `d local / d pts[k]` for the
    /// frame points and `out[HISTORY + 1]` is `d local / d q` (matrices acting on 3-vectors;
    /// in 2D only the top-left 2x2 block is used).
    fn local_with_jacobians(pts: &[Self], q: Self, min_seg: f64) -> Option<(Self, [DMat3; 4])>;
    /// Pose from a rotation matrix and a position.
    fn make_pose(r: DMat3, p: Self) -> Self::P;
    /// As a 3-vector (z = 0 in 2D).
    fn to3(self) -> DVec3;
    /// From a 3-vector (dropping z in 2D).
    fn from3(v: DVec3) -> Self;
}

impl CurveSpace for DVec2 {
    type P = Se2;
    const HISTORY: usize = 1;
    fn position_of(p: &Se2) -> Self {
        DVec2::new(p.x, p.y)
    }
    fn local(pts: &[Self], q: Self, min_seg: f64) -> Option<Self> {
        let d = pts[1] - pts[0];
        let n = d.length();
        if !(n > min_seg) {
            return None;
        }
        let x = d / n;
        let v = q - pts[1];
        Some(DVec2::new(x.dot(v), x.perp_dot(v)))
    }
    fn rotation_of(p: &Se2) -> DMat3 {
        DMat3::from_rotation_z(p.theta)
    }
    fn frame(pts: &[Self], min_seg: f64) -> Option<DMat3> {
        let d = pts[1] - pts[0];
        let n = d.length();
        if !(n > min_seg) {
            return None;
        }
        Some(DMat3::from_rotation_z(d.y.atan2(d.x)))
    }
    fn local_with_jacobians(pts: &[Self], q: Self, min_seg: f64) -> Option<(Self, [DMat3; 4])> {
        let d = pts[1] - pts[0];
        let n = d.length();
        if !(n > min_seg) {
            return None;
        }
        let x = d / n;
        let y = x.perp();
        let v = q - pts[1];
        let l = DVec2::new(x.dot(v), y.dot(v));
        // l0 = x.v, l1 = y.v with y = perp(x): d l / d x = [v; (v.y, -v.x)], d x / d d =
        // (I - x x^T) / n.
        let w = DVec2::new(v.y, -v.x);
        let g0 = (v - x * x.dot(v)) / n;
        let g1 = (w - x * x.dot(w)) / n;
        let jd = rows(g0.extend(0.0), g1.extend(0.0), DVec3::ZERO);
        let jq = rows(x.extend(0.0), y.extend(0.0), DVec3::ZERO);
        Some((l, [-jd, jd - jq, jq, DMat3::ZERO]))
    }
    fn make_pose(r: DMat3, p: Self) -> Se2 {
        Se2::new(p.x, p.y, r.col(0).y.atan2(r.col(0).x))
    }
    fn to3(self) -> DVec3 {
        self.extend(0.0)
    }
    fn from3(v: DVec3) -> Self {
        v.truncate()
    }
}

/// The matrix with these rows.
fn rows(r0: DVec3, r1: DVec3, r2: DVec3) -> DMat3 {
    DMat3::from_cols(r0, r1, r2).transpose()
}

fn frame3(pts: &[DVec3], min_seg: f64) -> Option<DMat3> {
    let d1 = pts[2] - pts[1];
    let d0 = pts[1] - pts[0];
    let n1 = d1.length();
    if !(n1 > min_seg) || !(d0.length() > min_seg) {
        return None;
    }
    let x = d1 / n1;
    let z = d0.cross(d1);
    let nz = z.length();
    // Collinear points: no plane.
    if !(nz > 1e-6 * n1 * d0.length()) {
        return None;
    }
    let z = z / nz;
    Some(DMat3::from_cols(x, z.cross(x), z))
}

impl CurveSpace for DVec3 {
    type P = Se3;
    const HISTORY: usize = 2;
    fn position_of(p: &Se3) -> Self {
        p.translation
    }
    fn local(pts: &[Self], q: Self, min_seg: f64) -> Option<Self> {
        frame3(pts, min_seg).map(|f| f.transpose() * (q - pts[2]))
    }
    fn rotation_of(p: &Se3) -> DMat3 {
        p.rotation_matrix()
    }
    fn frame(pts: &[Self], min_seg: f64) -> Option<DMat3> {
        frame3(pts, min_seg)
    }
    fn local_with_jacobians(pts: &[Self], q: Self, min_seg: f64) -> Option<(Self, [DMat3; 4])> {
        use crate::geometry::skew;
        let f = frame3(pts, min_seg)?;
        let (x, z) = (f.col(0), f.col(2));
        let d1 = pts[2] - pts[1];
        let d0 = pts[1] - pts[0];
        let n1 = d1.length();
        let zr = d0.cross(d1);
        let nz = zr.length();
        let v = q - pts[2];
        let outer = |a: DVec3| DMat3::from_cols(a * a.x, a * a.y, a * a.z);
        // x = d1/|d1|; z = normalise(d0 x d1); y = z x x.
        let jx_d1 = (DMat3::IDENTITY - outer(x)) / n1;
        let jz_zr = (DMat3::IDENTITY - outer(z)) / nz;
        let jz_d0 = jz_zr * -skew(d1);
        let jz_d1 = jz_zr * skew(d0);
        let jy_d0 = -skew(x) * jz_d0;
        let jy_d1 = -skew(x) * jz_d1 + skew(z) * jx_d1;
        // Row k of d l / d d = v^T (d axis_k / d d).
        let dl_d0 = rows(DVec3::ZERO, jy_d0.transpose() * v, jz_d0.transpose() * v);
        let dl_d1 = rows(
            jx_d1.transpose() * v,
            jy_d1.transpose() * v,
            jz_d1.transpose() * v,
        );
        let ft = f.transpose();
        let l = ft * v;
        Some((l, [-dl_d0, dl_d0 - dl_d1, dl_d1 - ft, ft]))
    }
    fn make_pose(r: DMat3, p: Self) -> Se3 {
        Se3::new(glam::DQuat::from_mat3(&super::lie::project_to_so3(r)), p)
    }
    fn to3(self) -> DVec3 {
        self
    }
    fn from3(v: DVec3) -> Self {
        v
    }
}

/// One curve constraint: `local(frame points, p_k) = expected_k` for each target point.
struct CurveFactor<S: CurveSpace> {
    vars: Vec<usize>,
    /// Number of frame variables (HISTORY + 1), first in `vars`.
    n_frame: usize,
    /// Expected local coordinates of the remaining variables, with their whitening
    /// (upper-triangular `L^T`, `n x n` row-major, n = spatial dimension).
    targets: Vec<(S, Vec<f64>)>,
    min_seg: f64,
}

impl<S: CurveSpace> CurveFactor<S> {
    /// Residual from the values of this factor's variables, in slot order.
    fn residual(&self, slots: &[S], r: &mut [f64]) {
        let n = S::DIM;
        let pts = &slots[..self.n_frame];
        for (k, (expected, lt)) in self.targets.iter().enumerate() {
            let q = slots[self.n_frame + k];
            // Degenerate frames give a large constant residual (the solver rejects the step).
            let e = match S::local(pts, q, self.min_seg) {
                Some(l) => (l.to3() - expected.to3()).to_array(),
                None => [1e6; 3],
            };
            for row in 0..n {
                let mut s = 0.0;
                for c in row..n {
                    s += lt[row * n + c] * e[c];
                }
                r[k * n + row] = s;
            }
        }
    }
}

impl<S: CurveSpace> Factor<S> for CurveFactor<S> {
    fn variables(&self) -> &[usize] {
        &self.vars
    }
    fn residual_dim(&self) -> usize {
        self.targets.len() * S::DIM
    }
    fn evaluate(&self, values: &[S], r: &mut [f64], jacobian: Option<&mut [f64]>) {
        let vals: Vec<S> = self.vars.iter().map(|&v| values[v]).collect();
        let Some(jac) = jacobian else {
            self.residual(&vals, r);
            return;
        };
        let n = S::DIM;
        let cols = self.vars.len() * n;
        jac.fill(0.0);
        let pts = &vals[..self.n_frame];
        for (k, (expected, lt)) in self.targets.iter().enumerate() {
            let q = vals[self.n_frame + k];
            let Some((l, js)) = S::local_with_jacobians(pts, q, self.min_seg) else {
                // Degenerate frame: constant residual, zero Jacobian (as in `residual`).
                for row in 0..n {
                    r[k * n + row] = (row..n).map(|c| lt[row * n + c] * 1e6).sum();
                }
                continue;
            };
            let e = (l.to3() - expected.to3()).to_array();
            for row in 0..n {
                let mut s = 0.0;
                for c in row..n {
                    s += lt[row * n + c] * e[c];
                }
                r[k * n + row] = s;
                // Jacobian row = (L^T J)[row] for the frame slots and the target slot.
                let slots = (0..self.n_frame)
                    .map(|f| (f, f))
                    .chain([(self.n_frame + k, S::HISTORY + 1)]);
                for (slot, which) in slots {
                    let jm = js[which];
                    for c in 0..n {
                        let mut acc = 0.0;
                        for m in row..n {
                            acc += lt[row * n + m] * jm.col(c)[m];
                        }
                        jac[(k * n + row) * cols + slot * n + c] = acc;
                    }
                }
            }
        }
    }
}

/// A curve graph built from a pose graph, ready to optimise and map back.
pub struct CurveGraph<S: CurveSpace> {
    /// Indices (into the pose graph) of the kept nodes, in chain order.
    pub kept: Vec<usize>,
    /// The position problem (one variable per kept node).
    pub problem: Problem<S>,
    phi: Vec<DMat3>,
    /// For every original vertex: (kept index it hangs from, offset kept_from_vertex).
    attach: Vec<(usize, S::P)>,
    original: Vec<S::P>,
    opts: CurveOptions,
}

fn cov_sum(a: &[f64], b: &[f64]) -> Vec<f64> {
    a.iter().zip(b).map(|(x, y)| x + y).collect()
}

impl<S: CurveSpace> CurveGraph<S>
where
    S::P: Pose,
{
    /// Builds the curve graph from a pose graph's current poses and edges.
    pub fn new(g: &PoseGraph<S::P>, opts: &CurveOptions) -> Result<Self, GraphError> {
        g.check_connected()?;
        let n = g.poses.len();
        let pd = <S::P as Manifold>::DIM;
        let sd = S::DIM;
        if n < S::HISTORY + 2 {
            return Err(GraphError::Invalid(
                "too few vertices for a curve graph".into(),
            ));
        }
        // Nodes in non-consecutive (loop) edges are always kept.
        let mut must = vec![false; n];
        for e in &g.edges {
            if e.to != e.from + 1 && e.from != e.to + 1 {
                must[e.from] = true;
                must[e.to] = true;
            }
        }
        // A node is kept only if it moved more than 10 x min_segment from the last kept node
        // (otherwise its curve frame would be degenerate: e.g. a robot turning on the spot);
        // then loop nodes always, others when they pass th_d or th_theta. Dropped nodes hang
        // rigidly from the last kept node, and their loop edges are moved onto it.
        let seg = opts.min_segment * 10.0;
        let mut kept = Vec::new();
        let mut last = 0usize;
        for i in 0..n {
            let keep = if i == 0 {
                true
            } else {
                let rel = g.poses[last].inverse().compose(&g.poses[i]);
                let dist = rel.position().length();
                let r = S::rotation_of(&rel);
                let angle = ((r.col(0).x + r.col(1).y + r.col(2).z - 1.0) / 2.0)
                    .clamp(-1.0, 1.0)
                    .acos();
                dist > seg
                    && (must[i]
                        || dist >= opts.th_d
                        || (opts.th_theta > 0.0 && angle >= opts.th_theta))
            };
            if keep {
                kept.push(i);
                last = i;
            }
        }
        let mut kidx = vec![usize::MAX; n];
        for (k, &i) in kept.iter().enumerate() {
            kidx[i] = k;
        }
        let mut attach = Vec::with_capacity(n);
        let mut cur = 0;
        for i in 0..n {
            if kidx[i] != usize::MAX {
                cur = kidx[i];
            }
            attach.push((cur, g.poses[kept[cur]].inverse().compose(&g.poses[i])));
        }
        // Positions and frames.
        let pos: Vec<S> = kept.iter().map(|&i| S::position_of(&g.poses[i])).collect();
        let mut phi = vec![DMat3::IDENTITY; kept.len()];
        for k in S::HISTORY..kept.len() {
            let c = S::frame(&pos[k - S::HISTORY..=k], opts.min_segment).ok_or_else(|| {
                GraphError::DegenerateSegment(format!(
                    "frame of vertex {} (collinear or coincident positions; raise th_d)",
                    g.ids[kept[k]]
                ))
            })?;
            phi[k] = c.transpose() * S::rotation_of(&g.poses[kept[k]]);
        }
        let mut problem = Problem::new();
        for (k, p) in pos.iter().enumerate() {
            problem.add_variable(*p);
            if k < S::HISTORY + 1 {
                problem.set_fixed(k, true);
            }
        }
        // Edges between kept nodes: loop edges directly, chain edges composed.
        let mut rel_edges: Vec<(usize, usize, S::P, Vec<f64>)> = Vec::new();
        let mut chain_cov: Vec<Option<(S::P, Vec<f64>)>> = vec![None; n];
        for e in &g.edges {
            let cov = spd_inverse(&e.information, pd).ok_or(
                GraphError::InformationNotPositiveDefinite {
                    from: g.ids[e.from],
                    to: g.ids[e.to],
                },
            )?;
            if e.to == e.from + 1 {
                chain_cov[e.to] = Some((e.measurement, cov));
            } else if e.from == e.to + 1 {
                chain_cov[e.from] = Some((e.measurement.inverse(), cov));
            } else {
                // x_a = x_ka o_a and x_b = x_kb o_b, so x_ka^-1 x_kb = o_a z o_b^-1.
                let (ka, oa) = &attach[e.from];
                let (kb, ob) = &attach[e.to];
                if ka != kb {
                    let z = oa.compose(&e.measurement).compose(&ob.inverse());
                    rel_edges.push((*ka, *kb, z, cov));
                }
            }
        }
        for w in kept.windows(2) {
            let (a, b) = (w[0], w[1]);
            let mut z = S::P::identity();
            let mut cov = vec![0.0; pd * pd];
            for i in a + 1..=b {
                let Some((zi, ci)) = &chain_cov[i] else {
                    return Err(GraphError::Invalid(format!(
                        "no odometry edge into vertex {}",
                        g.ids[i]
                    )));
                };
                z = z.compose(zi);
                cov = cov_sum(&cov, ci);
            }
            rel_edges.push((kidx[a], kidx[b], z, cov));
        }
        for (a, b, z, cov) in rel_edges {
            // Reference node must have a frame; otherwise use the reverse edge.
            let (a, b, z) = if a >= S::HISTORY {
                (a, b, z)
            } else if b >= S::HISTORY {
                (b, a, z.inverse())
            } else {
                continue;
            };
            let mut vars: Vec<usize> = (a - S::HISTORY..=a).collect();
            let n_frame = vars.len();
            let mut targets = Vec::new();
            // Translation covariance (in a's pose frame) and rotation variance.
            let mut ct = vec![0.0; sd * sd];
            for r in 0..sd {
                for c in 0..sd {
                    ct[r * sd + c] = cov[r * pd + c];
                }
            }
            let rot_var = if sd == 2 {
                cov[2 * pd + 2]
            } else {
                (cov[3 * pd + 3] + cov[4 * pd + 4] + cov[5 * pd + 5]) / 3.0
            };
            let zb = z;
            for back in 0..=S::HISTORY {
                if b < back {
                    break;
                }
                let t = b - back;
                if vars.contains(&t) {
                    continue;
                }
                // Expected position of node t in a's pose frame, then a's curve frame.
                let in_b = if back == 0 {
                    S::P::identity()
                } else {
                    g.poses[kept[b]].inverse().compose(&g.poses[kept[t]])
                };
                let pa = zb.compose(&in_b).position();
                let expected = S::from3(phi[a] * pa);
                // Whitening: translation covariance (+ lever-arm term for predecessors),
                // rotated into the curve frame.
                let lever = in_b.position().length_squared();
                let mut c3 = ct.clone();
                for d in 0..sd {
                    c3[d * sd + d] += lever * rot_var;
                }
                let phi_s: Vec<f64> = (0..sd * sd).map(|k| phi[a].col(k % sd)[k / sd]).collect();
                // C = Phi c3 Phi^T
                let mut cr = vec![0.0; sd * sd];
                for r in 0..sd {
                    for c in 0..sd {
                        let mut s = 0.0;
                        for i in 0..sd {
                            for j in 0..sd {
                                s += phi_s[r * sd + i] * c3[i * sd + j] * phi_s[c * sd + j];
                            }
                        }
                        cr[r * sd + c] = s;
                    }
                }
                let info =
                    spd_inverse(&cr, sd).ok_or(GraphError::InformationNotPositiveDefinite {
                        from: a as i64,
                        to: b as i64,
                    })?;
                let l = super::lie::cholesky_lower(&info, sd).ok_or(
                    GraphError::InformationNotPositiveDefinite {
                        from: a as i64,
                        to: b as i64,
                    },
                )?;
                let lt: Vec<f64> = (0..sd * sd).map(|k| l[(k % sd) * sd + k / sd]).collect();
                vars.push(t);
                targets.push((expected, lt));
            }
            if targets.is_empty() {
                continue;
            }
            problem.add_factor(Box::new(CurveFactor::<S> {
                vars,
                n_frame,
                targets,
                min_seg: opts.min_segment,
            }))?;
        }
        Ok(CurveGraph {
            kept,
            problem,
            phi,
            attach,
            original: g.poses.clone(),
            opts: opts.clone(),
        })
    }

    /// Optimises the positions.
    pub fn optimize(&mut self, opts: &SolverOptions) -> Result<SolveReport, GraphError> {
        self.problem.optimize(opts)
    }

    /// Full poses for every original vertex: kept nodes from their curve frames, the first
    /// (fixed) ones keep their rotation, dropped nodes hang rigidly from their kept node.
    pub fn poses(&self) -> Vec<S::P> {
        let pos = &self.problem.values;
        let mut kept_poses = Vec::with_capacity(pos.len());
        for k in 0..pos.len() {
            let r = if k >= S::HISTORY {
                match S::frame(&pos[k - S::HISTORY..=k], self.opts.min_segment) {
                    Some(c) => c * self.phi[k],
                    None => S::rotation_of(&self.original[self.kept[k]]),
                }
            } else {
                S::rotation_of(&self.original[self.kept[k]])
            };
            kept_poses.push(S::make_pose(r, pos[k]));
        }
        self.attach
            .iter()
            .map(|(k, off)| kept_poses[*k].compose(off))
            .collect()
    }
}

/// Curve graph in R^2 from an SE(2) graph.
pub type CurveGraph2 = CurveGraph<DVec2>;
/// Curve graph in R^3 from an SE(3) graph.
pub type CurveGraph3 = CurveGraph<DVec3>;

#[cfg(test)]
mod tests {
    use super::*;

    /// Central differences of the factor's residual against its analytic Jacobian.
    fn check_factor<S: CurveSpace>(f: &CurveFactor<S>, values: &[S]) {
        let m = f.residual_dim();
        let d = S::DIM;
        let cols = f.vars.len() * d;
        let mut r = vec![0.0; m];
        let mut jac = vec![0.0; m * cols];
        f.evaluate(values, &mut r, Some(&mut jac));
        let mut r_plain = vec![0.0; m];
        f.evaluate(values, &mut r_plain, None);
        assert_eq!(r, r_plain);
        let h = 1e-6;
        for (slot, &var) in f.vars.iter().enumerate() {
            for c in 0..d {
                let mut delta = [0.0; 3];
                let mut vp = values.to_vec();
                delta[c] = h;
                vp[var] = values[var].retract(&delta[..d]);
                let mut rp = vec![0.0; m];
                f.evaluate(&vp, &mut rp, None);
                delta[c] = -h;
                vp[var] = values[var].retract(&delta[..d]);
                let mut rm = vec![0.0; m];
                f.evaluate(&vp, &mut rm, None);
                for row in 0..m {
                    let fd = (rp[row] - rm[row]) / (2.0 * h);
                    let an = jac[row * cols + slot * d + c];
                    assert!(
                        (fd - an).abs() < 1e-6 * (1.0 + fd.abs()),
                        "slot {slot} coord {c} row {row}: fd {fd} analytic {an}"
                    );
                }
            }
        }
    }

    #[test]
    fn curve_jacobians_match_finite_differences_2d() {
        let values = vec![
            DVec2::new(0.1, 0.2),
            DVec2::new(1.3, 0.5),
            DVec2::new(2.0, 1.7),
            DVec2::new(1.1, 2.9),
        ];
        let f = CurveFactor::<DVec2> {
            vars: vec![0, 1, 3, 2],
            n_frame: 2,
            targets: vec![
                (DVec2::new(0.4, 1.0), vec![2.0, 0.3, 0.0, 1.5]),
                (DVec2::new(-0.2, 0.7), vec![1.0, -0.4, 0.0, 0.8]),
            ],
            min_seg: 1e-6,
        };
        check_factor(&f, &values);
    }

    #[test]
    fn curve_jacobians_match_finite_differences_3d() {
        let values = vec![
            DVec3::new(0.1, 0.2, -0.3),
            DVec3::new(1.3, 0.5, 0.1),
            DVec3::new(2.0, 1.7, 0.4),
            DVec3::new(1.1, 2.9, 1.2),
            DVec3::new(-0.5, 1.0, 2.0),
        ];
        let lt = vec![2.0, 0.3, -0.1, 0.0, 1.5, 0.2, 0.0, 0.0, 0.7];
        let f = CurveFactor::<DVec3> {
            vars: vec![0, 1, 2, 4, 3],
            n_frame: 3,
            targets: vec![
                (DVec3::new(0.4, 1.0, -0.2), lt.clone()),
                (DVec3::new(-0.2, 0.7, 0.3), lt),
            ],
            min_seg: 1e-6,
        };
        check_factor(&f, &values);
    }
}
