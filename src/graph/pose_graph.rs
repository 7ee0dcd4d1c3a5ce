//! Pose graphs in SE(2), SE(3) and Sim(3) (thesis 7.3, eq. 7.1-7.6): vertices are
//! `world_from_body` transforms, edges relative measurements `from_from_to` with an
//! information matrix. Residual of an edge `(i, j, Z, Omega)`: the error transform
//! `E = Z^-1 (X_i^-1 X_j)` mapped to a vector,
//! SE(2): `(E.x, E.y, wrap(E.theta))` (the g2o error);
//! SE(3): `[E.t; Log(E.R)]` (translation first, as g2o orders its information);
//! Sim(3): `[E.t; Log(E.R); ln E.s]`.
//! The cost is `chi2 = sum e^T Omega e`. For SE(3) the rotation block of Omega weights the
//! rotation vector (as GTSAM and the SE-Sync objective read g2o files); g2o's own chi2 uses the
//! quaternion vector part instead (about half the angle), see [`PoseGraph::chi2_g2o_quaternion`].

use std::collections::{HashMap, VecDeque};

use glam::{DMat3, DVec3};

use super::lie::{
    cholesky_lower, so3_right_jacobian_inverse, spd_inverse, wrap_angle, Manifold, Se2, Sim3,
};
use super::solver::{Factor, Problem, SolveReport, SolverOptions};
use super::GraphError;
use crate::geometry::{skew, so3_log, Covariance6, Se3};

/// A pose type usable as a pose-graph vertex.
pub trait Pose: Manifold + Copy + std::fmt::Debug {
    /// The identity.
    fn identity() -> Self;
    /// `self * rhs`.
    fn compose(&self, rhs: &Self) -> Self;
    /// Inverse.
    fn inverse(&self) -> Self;
    /// Position (metres, zero z in 2D).
    fn position(&self) -> DVec3;
    /// Residual of the edge `Z` between `xi` and `xj` (length `DIM`), and when asked the
    /// Jacobians `d e / d delta_i` and `d e / d delta_j` (row-major `DIM x DIM` each).
    fn edge_residual(
        xi: &Self,
        xj: &Self,
        z: &Self,
        e: &mut [f64],
        jac: Option<(&mut [f64], &mut [f64])>,
    );
}

fn put3(m: &mut [f64], stride: usize, r0: usize, c0: usize, a: DMat3) {
    for r in 0..3 {
        for c in 0..3 {
            m[(r0 + r) * stride + c0 + c] = a.col(c)[r];
        }
    }
}

impl Pose for Se2 {
    fn identity() -> Self {
        Se2::IDENTITY
    }
    fn compose(&self, rhs: &Self) -> Self {
        Se2::compose(self, rhs)
    }
    fn inverse(&self) -> Self {
        Se2::inverse(self)
    }
    fn position(&self) -> DVec3 {
        DVec3::new(self.x, self.y, 0.0)
    }
    fn edge_residual(
        xi: &Self,
        xj: &Self,
        z: &Self,
        e: &mut [f64],
        jac: Option<(&mut [f64], &mut [f64])>,
    ) {
        let (si, ci) = xi.theta.sin_cos();
        let (sz, cz) = z.theta.sin_cos();
        let dx = xj.x - xi.x;
        let dy = xj.y - xi.y;
        // a = Ri^T dt - tz ; e_t = Rz^T a
        let ax = ci * dx + si * dy - z.x;
        let ay = -si * dx + ci * dy - z.y;
        e[0] = cz * ax + sz * ay;
        e[1] = -sz * ax + cz * ay;
        e[2] = wrap_angle(xj.theta - xi.theta - z.theta);
        if let Some((ji, jj)) = jac {
            // M = Rz^T Ri^T
            let c = ci * cz - si * sz; // cos(thi + thz)
            let s = si * cz + ci * sz; // sin(thi + thz)
                                       // d(Ri^T dt)/d thi = [-si dx + ci dy, -ci dx - si dy]
            let gx = -si * dx + ci * dy;
            let gy = -ci * dx - si * dy;
            let m = [[c, s], [-s, c]];
            ji.copy_from_slice(&[
                -m[0][0],
                -m[0][1],
                cz * gx + sz * gy,
                -m[1][0],
                -m[1][1],
                -sz * gx + cz * gy,
                0.0,
                0.0,
                -1.0,
            ]);
            jj.copy_from_slice(&[m[0][0], m[0][1], 0.0, m[1][0], m[1][1], 0.0, 0.0, 0.0, 1.0]);
        }
    }
}

impl Pose for Se3 {
    fn identity() -> Self {
        Se3::IDENTITY
    }
    fn compose(&self, rhs: &Self) -> Self {
        *self * *rhs
    }
    fn inverse(&self) -> Self {
        Se3::inverse(self)
    }
    fn position(&self) -> DVec3 {
        self.translation
    }
    fn edge_residual(
        xi: &Self,
        xj: &Self,
        z: &Self,
        e: &mut [f64],
        jac: Option<(&mut [f64], &mut [f64])>,
    ) {
        let rit = xi.rotation.conjugate();
        let rzt = z.rotation.conjugate();
        let a = rit * (xj.translation - xi.translation);
        let et = rzt * (a - z.translation);
        let er_q = rzt * rit * xj.rotation;
        let er = so3_log(er_q);
        e[..3].copy_from_slice(&et.to_array());
        e[3..6].copy_from_slice(&er.to_array());
        if let Some((ji, jj)) = jac {
            let rz_t = DMat3::from_quat(rzt);
            let rij = DMat3::from_quat(rit * xj.rotation); // Ri^T Rj
            let jr_inv = so3_right_jacobian_inverse(er);
            ji.fill(0.0);
            jj.fill(0.0);
            put3(ji, 6, 0, 0, -rz_t);
            put3(ji, 6, 0, 3, rz_t * skew(a));
            put3(ji, 6, 3, 3, -(jr_inv * rij.transpose()));
            put3(jj, 6, 0, 0, rz_t * rij);
            put3(jj, 6, 3, 3, jr_inv);
        }
    }
}

impl Pose for Sim3 {
    fn identity() -> Self {
        Sim3::IDENTITY
    }
    fn compose(&self, rhs: &Self) -> Self {
        Sim3::compose(self, rhs)
    }
    fn inverse(&self) -> Self {
        Sim3::inverse(self)
    }
    fn position(&self) -> DVec3 {
        self.translation
    }
    fn edge_residual(
        xi: &Self,
        xj: &Self,
        z: &Self,
        e: &mut [f64],
        jac: Option<(&mut [f64], &mut [f64])>,
    ) {
        let rit = xi.rotation.conjugate();
        let rzt = z.rotation.conjugate();
        let k = 1.0 / (z.scale * xi.scale);
        let a = rit * (xj.translation - xi.translation); // Ri^T (tj - ti)
        let et = rzt * (a / xi.scale - z.translation) / z.scale;
        let er = so3_log(rzt * rit * xj.rotation);
        e[..3].copy_from_slice(&et.to_array());
        e[3..6].copy_from_slice(&er.to_array());
        e[6] = xj.scale.ln() - xi.scale.ln() - z.scale.ln();
        if let Some((ji, jj)) = jac {
            let rz_t = DMat3::from_quat(rzt);
            let rij = DMat3::from_quat(rit * xj.rotation);
            let jr_inv = so3_right_jacobian_inverse(er);
            ji.fill(0.0);
            jj.fill(0.0);
            put3(ji, 7, 0, 0, -(rz_t * k));
            put3(ji, 7, 0, 3, rz_t * skew(a) * k);
            let ds = -(rz_t * a) * k;
            for r in 0..3 {
                ji[r * 7 + 6] = ds[r];
            }
            put3(ji, 7, 3, 3, -(jr_inv * rij.transpose()));
            ji[6 * 7 + 6] = -1.0;
            put3(jj, 7, 0, 0, rz_t * rij * k);
            put3(jj, 7, 3, 3, jr_inv);
            jj[6 * 7 + 6] = 1.0;
        }
    }
}

/// A relative-pose measurement between two vertices (indices into the graph's vertex list).
#[derive(Clone, Debug)]
pub struct Edge<P: Pose> {
    /// Index of the first vertex.
    pub from: usize,
    /// Index of the second vertex.
    pub to: usize,
    /// Measured `from_from_to`.
    pub measurement: P,
    /// Information matrix, row-major `DIM x DIM`, ordered like the residual.
    pub information: Vec<f64>,
}

/// A pose graph: vertices with external ids, initial/current poses, fixed flags and edges.
#[derive(Clone, Debug)]
pub struct PoseGraph<P: Pose> {
    /// External vertex ids (as in the file), one per vertex.
    pub ids: Vec<i64>,
    /// Current `world_from_body` poses.
    pub poses: Vec<P>,
    /// Fixed (gauge) vertices.
    pub fixed: Vec<bool>,
    /// Edges.
    pub edges: Vec<Edge<P>>,
    index: HashMap<i64, usize>,
}

impl<P: Pose> Default for PoseGraph<P> {
    fn default() -> Self {
        Self::new()
    }
}

/// SE(2) pose graph.
pub type PoseGraph2 = PoseGraph<Se2>;
/// SE(3) pose graph.
pub type PoseGraph3 = PoseGraph<Se3>;
/// Sim(3) pose graph.
pub type PoseGraphSim3 = PoseGraph<Sim3>;

struct EdgeFactor<P: Pose> {
    vars: [usize; 2],
    z: P,
    /// Upper-triangular `L^T` (row-major) with `Omega = L L^T`.
    sqrt_info_t: Vec<f64>,
}

impl<P: Pose> Factor<P> for EdgeFactor<P> {
    fn variables(&self) -> &[usize] {
        &self.vars
    }
    fn residual_dim(&self) -> usize {
        P::DIM
    }
    fn evaluate(&self, values: &[P], r: &mut [f64], jacobian: Option<&mut [f64]>) {
        let d = P::DIM;
        let mut e = [0.0; 8];
        let xi = &values[self.vars[0]];
        let xj = &values[self.vars[1]];
        match jacobian {
            None => P::edge_residual(xi, xj, &self.z, &mut e[..d], None),
            Some(jac) => {
                let mut ji = [0.0; 64];
                let mut jj = [0.0; 64];
                P::edge_residual(
                    xi,
                    xj,
                    &self.z,
                    &mut e[..d],
                    Some((&mut ji[..d * d], &mut jj[..d * d])),
                );
                // jac = L^T [Ji Jj], rows d, cols 2d.
                for row in 0..d {
                    for c in 0..d {
                        let mut si = 0.0;
                        let mut sj = 0.0;
                        for k in row..d {
                            let l = self.sqrt_info_t[row * d + k];
                            si += l * ji[k * d + c];
                            sj += l * jj[k * d + c];
                        }
                        jac[row * 2 * d + c] = si;
                        jac[row * 2 * d + d + c] = sj;
                    }
                }
            }
        }
        for row in 0..d {
            let mut s = 0.0;
            for k in row..d {
                s += self.sqrt_info_t[row * d + k] * e[k];
            }
            r[row] = s;
        }
    }
}

impl<P: Pose> PoseGraph<P> {
    /// Bytes of heap memory the graph holds (vertices, edges with their information
    /// matrices, the id index counted at its capacity times its entry size).
    pub(crate) fn heap_bytes(&self) -> usize {
        fn bytes<T>(v: &Vec<T>) -> usize {
            v.capacity() * std::mem::size_of::<T>()
        }
        bytes(&self.ids)
            + bytes(&self.poses)
            + bytes(&self.fixed)
            + bytes(&self.edges)
            + self
                .edges
                .iter()
                .map(|e| bytes(&e.information))
                .sum::<usize>()
            + self.index.capacity() * std::mem::size_of::<(i64, usize)>()
    }

    /// An empty graph.
    pub fn new() -> Self {
        PoseGraph {
            ids: Vec::new(),
            poses: Vec::new(),
            fixed: Vec::new(),
            edges: Vec::new(),
            index: HashMap::new(),
        }
    }
    /// Adds a vertex; errors on a duplicate id or a non-finite pose. Returns its index.
    pub fn add_vertex(&mut self, id: i64, pose: P) -> Result<usize, GraphError> {
        if self.index.contains_key(&id) {
            return Err(GraphError::DuplicateVertex(id));
        }
        if !pose.is_finite() {
            return Err(GraphError::NonFinite(format!("pose of vertex {id}")));
        }
        self.index.insert(id, self.ids.len());
        self.ids.push(id);
        self.poses.push(pose);
        self.fixed.push(false);
        Ok(self.ids.len() - 1)
    }
    /// Index of the vertex with external id `id`.
    pub fn index_of(&self, id: i64) -> Option<usize> {
        self.index.get(&id).copied()
    }
    /// Adds an edge between vertex ids; the information matrix must be symmetric positive
    /// definite (row-major `DIM x DIM`).
    pub fn add_edge(
        &mut self,
        from_id: i64,
        to_id: i64,
        measurement: P,
        information: Vec<f64>,
    ) -> Result<usize, GraphError> {
        let from = self
            .index_of(from_id)
            .ok_or(GraphError::UnknownVertex(from_id))?;
        let to = self
            .index_of(to_id)
            .ok_or(GraphError::UnknownVertex(to_id))?;
        self.add_edge_by_index(from, to, measurement, information)
    }
    /// Like [`PoseGraph::add_edge`] with vertex indices.
    pub fn add_edge_by_index(
        &mut self,
        from: usize,
        to: usize,
        measurement: P,
        information: Vec<f64>,
    ) -> Result<usize, GraphError> {
        let d = P::DIM;
        let n = self.poses.len();
        if from >= n || to >= n {
            return Err(GraphError::UnknownVertex(from.max(to) as i64));
        }
        if from == to {
            return Err(GraphError::Invalid(format!(
                "self-loop edge on vertex {}",
                self.ids[from]
            )));
        }
        if !measurement.is_finite() {
            return Err(GraphError::NonFinite(format!(
                "measurement of edge {}-{}",
                self.ids[from], self.ids[to]
            )));
        }
        if information.len() != d * d || cholesky_lower(&information, d).is_none() {
            return Err(GraphError::InformationNotPositiveDefinite {
                from: self.ids[from],
                to: self.ids[to],
            });
        }
        for r in 0..d {
            for c in 0..r {
                let (a, b) = (information[r * d + c], information[c * d + r]);
                if (a - b).abs() > 1e-9 * (1.0 + a.abs().max(b.abs())) {
                    return Err(GraphError::InformationNotPositiveDefinite {
                        from: self.ids[from],
                        to: self.ids[to],
                    });
                }
            }
        }
        self.edges.push(Edge {
            from,
            to,
            measurement,
            information,
        });
        Ok(self.edges.len() - 1)
    }

    /// Vertex indices reachable from `root` through edges.
    fn component_of(&self, root: usize) -> Vec<bool> {
        let adj = self.adjacency();
        let mut seen = vec![false; self.poses.len()];
        let mut q = VecDeque::from([root]);
        seen[root] = true;
        while let Some(i) = q.pop_front() {
            for &(j, _, _) in &adj[i] {
                if !seen[j] {
                    seen[j] = true;
                    q.push_back(j);
                }
            }
        }
        seen
    }

    /// Adjacency lists `(neighbour, edge index, edge goes i->j)`.
    pub(crate) fn adjacency(&self) -> Vec<Vec<(usize, usize, bool)>> {
        let mut adj = vec![Vec::new(); self.poses.len()];
        for (k, e) in self.edges.iter().enumerate() {
            adj[e.from].push((e.to, k, true));
            adj[e.to].push((e.from, k, false));
        }
        adj
    }

    /// The gauge: the fixed vertices, or the first vertex when none is fixed. Errors when the
    /// graph is empty or not connected to the gauge.
    pub fn check_connected(&self) -> Result<usize, GraphError> {
        if self.poses.is_empty() {
            return Err(GraphError::Invalid("empty graph".into()));
        }
        let root = self.fixed.iter().position(|&f| f).unwrap_or(0);
        let seen = self.component_of(root);
        // Every component must contain a fixed vertex (or be the root's).
        let mut seen_all = seen.clone();
        for (i, &f) in self.fixed.iter().enumerate() {
            if f && !seen_all[i] {
                let s = self.component_of(i);
                for (a, b) in seen_all.iter_mut().zip(s) {
                    *a |= b;
                }
            }
        }
        if let Some(bad) = seen_all.iter().position(|s| !s) {
            return Err(GraphError::Disconnected {
                vertex: self.ids[bad],
            });
        }
        Ok(root)
    }

    /// Spanning-tree (odometry) initial estimate: breadth-first from the gauge vertex,
    /// composing edge measurements; poses not reached keep their value.
    pub fn initialize_spanning_tree(&mut self) -> Result<(), GraphError> {
        let root = self.check_connected()?;
        let adj = self.adjacency();
        let mut seen = vec![false; self.poses.len()];
        let mut q = VecDeque::from([root]);
        seen[root] = true;
        while let Some(i) = q.pop_front() {
            for &(j, k, forward) in &adj[i] {
                if seen[j] {
                    continue;
                }
                let z = self.edges[k].measurement;
                self.poses[j] = if forward {
                    self.poses[i].compose(&z)
                } else {
                    self.poses[i].compose(&z.inverse())
                };
                seen[j] = true;
                q.push_back(j);
            }
        }
        Ok(())
    }

    /// A solver problem with this graph's poses as variables and no factors yet (the gauge
    /// vertex fixed); fails when the graph is not connected.
    fn problem_variables(&self) -> Result<Problem<P>, GraphError> {
        let root = self.check_connected()?;
        let mut p = Problem::new();
        for (i, x) in self.poses.iter().enumerate() {
            p.add_variable(*x);
            p.set_fixed(i, self.fixed[i]);
        }
        p.set_fixed(root, true);
        Ok(p)
    }

    /// A solver problem over this graph's poses (the first vertex fixed when none is).
    pub fn to_problem(&self) -> Result<Problem<P>, GraphError> {
        let mut p = self.problem_variables()?;
        for k in 0..self.edges.len() {
            p.add_factor(self.edge_factor(k)?)?;
        }
        Ok(p)
    }

    /// The solver factor of edge `k` (whitened by its information matrix).
    pub fn edge_factor(&self, k: usize) -> Result<Box<dyn Factor<P>>, GraphError> {
        let d = P::DIM;
        let e = self
            .edges
            .get(k)
            .ok_or_else(|| GraphError::Invalid(format!("no edge {k}")))?;
        let l = cholesky_lower(&e.information, d).ok_or(
            GraphError::InformationNotPositiveDefinite {
                from: self.ids[e.from],
                to: self.ids[e.to],
            },
        )?;
        let mut lt = vec![0.0; d * d];
        for r in 0..d {
            for c in 0..d {
                lt[r * d + c] = l[c * d + r];
            }
        }
        Ok(Box::new(EdgeFactor {
            vars: [e.from, e.to],
            z: e.measurement,
            sqrt_info_t: lt,
        }))
    }

    /// Optimises the poses in place (first vertex fixed when none is).
    pub fn optimize(&mut self, opts: &SolverOptions) -> Result<SolveReport, GraphError> {
        let mut p = self.to_problem()?;
        let rep = p.optimize(opts)?;
        self.poses = p.values;
        Ok(rep)
    }

    /// The error vector of edge `k` at the current poses.
    pub fn edge_error(&self, k: usize) -> Vec<f64> {
        let e = &self.edges[k];
        let mut v = vec![0.0; P::DIM];
        P::edge_residual(
            &self.poses[e.from],
            &self.poses[e.to],
            &e.measurement,
            &mut v,
            None,
        );
        v
    }

    /// `chi2 = sum e^T Omega e` at the current poses (see the module docs for `e`).
    pub fn chi2(&self) -> f64 {
        let d = P::DIM;
        (0..self.edges.len())
            .map(|k| {
                let e = self.edge_error(k);
                let om = &self.edges[k].information;
                let mut s = 0.0;
                for r in 0..d {
                    for c in 0..d {
                        s += e[r] * om[r * d + c] * e[c];
                    }
                }
                s
            })
            .sum()
    }

    /// Positions (metres) of all vertices.
    pub fn positions(&self) -> Vec<DVec3> {
        self.poses.iter().map(|p| p.position()).collect()
    }
}

/// Rotation matrix and translation of a pose as 3D quantities (2D poses embedded in z = 0).
pub trait RotationTranslation {
    /// `(R, t)` with `R` 3x3 (2D: rotation about z) and `t` in metres.
    fn rt(&self) -> (DMat3, DVec3);
    /// Spatial dimension (2 or 3).
    const SPACE_DIM: usize;
    /// Derivative of the world translation with respect to the translation part of the
    /// manifold increment (columns per increment coordinate): identity for SE(2), whose
    /// retraction adds in the world frame, and `R` for SE(3), which adds in the body frame.
    /// The rotation increment is always about body axes (`R exp([w]x)`).
    fn translation_tangent(&self) -> DMat3;
}
impl RotationTranslation for Se2 {
    fn rt(&self) -> (DMat3, DVec3) {
        (
            DMat3::from_rotation_z(self.theta),
            DVec3::new(self.x, self.y, 0.0),
        )
    }
    const SPACE_DIM: usize = 2;
    fn translation_tangent(&self) -> DMat3 {
        DMat3::IDENTITY
    }
}
impl RotationTranslation for Se3 {
    fn rt(&self) -> (DMat3, DVec3) {
        (self.rotation_matrix(), self.translation)
    }
    const SPACE_DIM: usize = 3;
    fn translation_tangent(&self) -> DMat3 {
        self.rotation_matrix()
    }
}

/// Which cost an SE(n) pose graph minimises.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum EdgeCost {
    /// The usual g2o / GTSAM cost: the geodesic error `log(Z^-1 Xi^-1 Xj)` whitened by the
    /// full information matrix (this is what `chi2` measures).
    #[default]
    Geodesic,
    /// The SE-Sync objective `F` (chordal rotation distance, isotropic weights kappa and tau
    /// from the information matrix; see [`PoseGraph::sesync_objective`]). Its optimum is the
    /// point SE-Sync's certified `f*` refers to; it differs from the geodesic optimum where
    /// the information is far from isotropic (CSAIL, cubicle).
    Chordal,
}

/// One edge of the SE-Sync objective: residual `[sqrt(tau) (tj - ti - Ri tij);
/// sqrt(kappa) vec(Rj - Ri Rij)]` over the spatial dimension `n` (`n + n^2` rows), so that
/// its squared norm is the edge's term of `F`.
struct ChordalFactor<P> {
    vars: [usize; 2],
    rz: DMat3,
    tz: DVec3,
    sqrt_kappa: f64,
    sqrt_tau: f64,
    _pose: std::marker::PhantomData<P>,
}

impl<P: Pose + RotationTranslation> Factor<P> for ChordalFactor<P> {
    fn variables(&self) -> &[usize] {
        &self.vars
    }
    fn residual_dim(&self) -> usize {
        P::SPACE_DIM + P::SPACE_DIM * P::SPACE_DIM
    }
    fn evaluate(&self, values: &[P], r: &mut [f64], jacobian: Option<&mut [f64]>) {
        let n = P::SPACE_DIM;
        let d = P::DIM;
        let xi = &values[self.vars[0]];
        let xj = &values[self.vars[1]];
        let (ri, ti) = xi.rt();
        let (rj, tj) = xj.rt();
        let dt = tj - ti - ri * self.tz;
        let dr = rj - ri * self.rz;
        for a in 0..n {
            r[a] = self.sqrt_tau * dt[a];
            for b in 0..n {
                r[n + a * n + b] = self.sqrt_kappa * dr.col(b)[a];
            }
        }
        let Some(jac) = jacobian else { return };
        jac.fill(0.0);
        let cols = 2 * d;
        // Translation increments.
        let (bi, bj) = (xi.translation_tangent(), xj.translation_tangent());
        for c in 0..n {
            for a in 0..n {
                jac[a * cols + c] = -self.sqrt_tau * bi.col(c)[a];
                jac[a * cols + d + c] = self.sqrt_tau * bj.col(c)[a];
            }
        }
        // Rotation increments about body axes: z only in 2D.
        let axes: &[usize] = if n == 2 { &[2] } else { &[0, 1, 2] };
        for (k, &axis) in axes.iter().enumerate() {
            let c = n + k;
            let mut e = DVec3::ZERO;
            e[axis] = 1.0;
            let ki = ri * skew(e);
            let kj = rj * skew(e);
            let dti = ki * self.tz;
            let dri = ki * self.rz;
            for a in 0..n {
                jac[a * cols + c] = -self.sqrt_tau * dti[a];
                for b in 0..n {
                    let row = (n + a * n + b) * cols;
                    jac[row + c] = -self.sqrt_kappa * dri.col(b)[a];
                    jac[row + d + c] = self.sqrt_kappa * kj.col(b)[a];
                }
            }
        }
    }
}

impl<P: Pose + RotationTranslation> PoseGraph<P> {
    /// A solver problem over this graph's poses with the chosen edge cost (the first vertex
    /// fixed when none is).
    pub fn to_problem_with(&self, cost: EdgeCost) -> Result<Problem<P>, GraphError> {
        if cost == EdgeCost::Geodesic {
            return self.to_problem();
        }
        let mut p = self.problem_variables()?;
        for e in &self.edges {
            let (kappa, tau) = sesync_weights(&e.information, P::SPACE_DIM, P::DIM);
            if !(kappa.is_finite() && tau.is_finite() && kappa > 0.0 && tau > 0.0) {
                return Err(GraphError::InformationNotPositiveDefinite {
                    from: self.ids[e.from],
                    to: self.ids[e.to],
                });
            }
            let (rz, tz) = e.measurement.rt();
            p.add_factor(Box::new(ChordalFactor::<P> {
                vars: [e.from, e.to],
                rz,
                tz,
                sqrt_kappa: kappa.sqrt(),
                sqrt_tau: tau.sqrt(),
                _pose: std::marker::PhantomData,
            }))?;
        }
        Ok(p)
    }

    /// Optimises the poses in place with the chosen edge cost.
    pub fn optimize_with(
        &mut self,
        opts: &SolverOptions,
        cost: EdgeCost,
    ) -> Result<SolveReport, GraphError> {
        let mut p = self.to_problem_with(cost)?;
        let rep = p.optimize(opts)?;
        self.poses = p.values;
        Ok(rep)
    }
}

impl<P: Pose + RotationTranslation> PoseGraph<P> {
    /// The SE-Sync objective `F = sum kappa ||Rj - Ri Rij||_F^2 + tau ||tj - ti - Ri tij||^2`
    /// with `tau = n / tr(It^-1)` and, in 2D, `kappa = I_theta`, in 3D
    /// `kappa = 3 / (2 tr(IR^-1))` (Rosen et al., IJRR 2019), comparable to their `f*`.
    pub fn sesync_objective(&self) -> f64 {
        let n = P::SPACE_DIM;
        let d = P::DIM;
        let mut f = 0.0;
        for e in &self.edges {
            let (kappa, tau) = sesync_weights(&e.information, n, d);
            let (ri, ti) = self.poses[e.from].rt();
            let (rj, tj) = self.poses[e.to].rt();
            let (rz, tz) = e.measurement.rt();
            let dr = rj - ri * rz;
            let fr: f64 = dr.to_cols_array().iter().map(|x| x * x).sum();
            let dt = tj - ti - ri * tz;
            // In 2D the embedded z row/column of the rotation contributes nothing (it is exact).
            f += kappa * fr + tau * dt.length_squared();
        }
        f
    }
}

/// `(kappa, tau)` of the SE-Sync objective from an information matrix (translation first).
pub fn sesync_weights(info: &[f64], n: usize, d: usize) -> (f64, f64) {
    let mut it = vec![0.0; n * n];
    for r in 0..n {
        for c in 0..n {
            it[r * n + c] = info[r * d + c];
        }
    }
    let tr_t: f64 = spd_inverse(&it, n)
        .map(|m| (0..n).map(|k| m[k * n + k]).sum())
        .unwrap_or(f64::INFINITY);
    let tau = n as f64 / tr_t;
    let kappa = if n == 2 {
        info[2 * d + 2]
    } else {
        let mut ir = [0.0; 9];
        for r in 0..3 {
            for c in 0..3 {
                ir[r * 3 + c] = info[(r + 3) * d + c + 3];
            }
        }
        let tr_r: f64 = spd_inverse(&ir, 3)
            .map(|m| m[0] + m[4] + m[8])
            .unwrap_or(f64::INFINITY);
        3.0 / (2.0 * tr_r)
    };
    (kappa, tau)
}

impl PoseGraph<Se3> {
    /// Adds an edge whose measurement `from_from_to` has the uncertainty `covariance` (the
    /// library's right perturbation, in the `to` frame; see [`Covariance6`]): its information
    /// matrix is the inverse covariance. A covariance that is not positive definite gives
    /// [`GraphError::InformationNotPositiveDefinite`].
    pub fn add_edge_with_covariance(
        &mut self,
        from_id: i64,
        to_id: i64,
        from_from_to: Se3,
        covariance: &Covariance6,
    ) -> Result<usize, GraphError> {
        let info = covariance
            .information()
            .ok_or(GraphError::InformationNotPositiveDefinite {
                from: from_id,
                to: to_id,
            })?;
        let info = info.iter().flatten().copied().collect();
        self.add_edge(from_id, to_id, from_from_to, info)
    }

    /// g2o's own chi2 for SE(3) edges: the error vector is `[E.t; q_xyz(E)]` (quaternion vector
    /// part with `w >= 0`) instead of the rotation vector.
    pub fn chi2_g2o_quaternion(&self) -> f64 {
        self.edges
            .iter()
            .map(|e| {
                let xi = &self.poses[e.from];
                let xj = &self.poses[e.to];
                let err = e.measurement.inverse() * (xi.inverse() * *xj);
                let q = if err.rotation.w < 0.0 {
                    -err.rotation
                } else {
                    err.rotation
                };
                let v = [
                    err.translation.x,
                    err.translation.y,
                    err.translation.z,
                    q.x,
                    q.y,
                    q.z,
                ];
                let mut s = 0.0;
                for r in 0..6 {
                    for c in 0..6 {
                        s += v[r] * e.information[r * 6 + c] * v[c];
                    }
                }
                s
            })
            .sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DQuat;

    #[test]
    fn se3_edges_take_a_covariance() {
        let mut g = PoseGraph3::default();
        g.add_vertex(0, Se3::IDENTITY).unwrap();
        g.add_vertex(1, Se3::IDENTITY).unwrap();
        let z = Se3::exp(&[0.1, 0.0, 0.0, 0.0, 0.0, 0.1]);
        let k = g
            .add_edge_with_covariance(0, 1, z, &Covariance6::from_sigmas(0.01, 0.002))
            .unwrap();
        let info = &g.edges[k].information;
        assert!((info[0] - 1e4).abs() < 1e-6 && (info[5 * 6 + 5] - 2.5e5).abs() < 1e-3);
        assert!(matches!(
            g.add_edge_with_covariance(0, 1, z, &Covariance6::ZERO),
            Err(GraphError::InformationNotPositiveDefinite { from: 0, to: 1 })
        ));
    }

    fn check_jacobians<P: Pose>(xi: P, xj: P, z: P, tol: f64) {
        let d = P::DIM;
        let mut e0 = vec![0.0; d];
        let mut ji = vec![0.0; d * d];
        let mut jj = vec![0.0; d * d];
        P::edge_residual(&xi, &xj, &z, &mut e0, Some((&mut ji, &mut jj)));
        let h = 1e-6;
        for c in 0..d {
            let mut delta = vec![0.0; d];
            delta[c] = h;
            let mut ep = vec![0.0; d];
            let mut em = vec![0.0; d];
            for (which, jac) in [(0, &ji), (1, &jj)] {
                let mut dm = delta.clone();
                dm[c] = -h;
                let (a, b) = if which == 0 {
                    (xi.retract(&delta), xj)
                } else {
                    (xi, xj.retract(&delta))
                };
                P::edge_residual(&a, &b, &z, &mut ep, None);
                let (a, b) = if which == 0 {
                    (xi.retract(&dm), xj)
                } else {
                    (xi, xj.retract(&dm))
                };
                P::edge_residual(&a, &b, &z, &mut em, None);
                for r in 0..d {
                    let fd = (ep[r] - em[r]) / (2.0 * h);
                    assert!(
                        (fd - jac[r * d + c]).abs() < tol,
                        "vertex {which} d e{r}/d{c}: fd {fd} analytic {}",
                        jac[r * d + c]
                    );
                }
            }
        }
    }

    #[test]
    fn se2_jacobians_match_finite_differences() {
        check_jacobians(
            Se2::new(1.0, -0.5, 0.8),
            Se2::new(2.5, 0.7, -2.0),
            Se2::new(0.9, 1.1, 0.4),
            1e-7,
        );
    }

    #[test]
    fn se3_jacobians_match_finite_differences() {
        let xi = Se3::new(
            DQuat::from_euler(glam::EulerRot::XYZ, 0.3, -0.5, 1.2),
            DVec3::new(1.0, 2.0, -0.5),
        );
        let xj = Se3::new(
            DQuat::from_euler(glam::EulerRot::XYZ, -0.7, 0.2, 2.0),
            DVec3::new(-1.0, 0.4, 0.9),
        );
        let z = Se3::new(
            DQuat::from_euler(glam::EulerRot::XYZ, 0.1, 0.9, -0.3),
            DVec3::new(0.3, -0.2, 0.1),
        );
        check_jacobians(xi, xj, z, 1e-6);
    }

    #[test]
    fn sim3_jacobians_match_finite_differences() {
        let xi = Sim3::new(
            DQuat::from_euler(glam::EulerRot::XYZ, 0.3, -0.5, 1.2),
            DVec3::new(1.0, 2.0, -0.5),
            1.3,
        );
        let xj = Sim3::new(
            DQuat::from_euler(glam::EulerRot::XYZ, -0.7, 0.2, 2.0),
            DVec3::new(-1.0, 0.4, 0.9),
            0.7,
        );
        let z = Sim3::new(
            DQuat::from_euler(glam::EulerRot::XYZ, 0.1, 0.9, -0.3),
            DVec3::new(0.3, -0.2, 0.1),
            1.1,
        );
        check_jacobians(xi, xj, z, 1e-6);
    }

    fn check_chordal_jacobians<P: Pose + RotationTranslation>(xi: P, xj: P, z: P, info: Vec<f64>) {
        let mut g = PoseGraph::<P>::new();
        g.add_vertex(0, xi).unwrap();
        g.add_vertex(1, xj).unwrap();
        g.add_edge(0, 1, z, info).unwrap();
        g.add_vertex(2, xj).unwrap();
        g.add_edge(1, 2, z, identity_info(P::DIM)).unwrap();
        let p = g.to_problem_with(EdgeCost::Chordal).unwrap();
        let f = &p.factors()[0];
        let m = f.residual_dim();
        let d = P::DIM;
        let mut r0 = vec![0.0; m];
        let mut jac = vec![0.0; m * 2 * d];
        let vals = vec![xi, xj];
        f.evaluate(&vals, &mut r0, Some(&mut jac));
        // F of this edge is |r|^2.
        let mut g1 = g.clone();
        g1.edges.truncate(1);
        assert!((r0.iter().map(|v| v * v).sum::<f64>() - g1.sesync_objective()).abs() < 1e-9);
        let h = 1e-6;
        for slot in 0..2 {
            for c in 0..d {
                let mut delta = vec![0.0; d];
                delta[c] = h;
                let mut vp = vals.clone();
                vp[slot] = vals[slot].retract(&delta);
                let mut rp = vec![0.0; m];
                f.evaluate(&vp, &mut rp, None);
                delta[c] = -h;
                vp[slot] = vals[slot].retract(&delta);
                let mut rm = vec![0.0; m];
                f.evaluate(&vp, &mut rm, None);
                for row in 0..m {
                    let fd = (rp[row] - rm[row]) / (2.0 * h);
                    let an = jac[row * 2 * d + slot * d + c];
                    assert!(
                        (fd - an).abs() < 1e-6,
                        "slot {slot} row {row} col {c}: fd {fd} analytic {an}"
                    );
                }
            }
        }
    }

    #[test]
    fn chordal_jacobians_match_finite_differences() {
        let mut info2 = identity_info(3);
        info2[0] = 4.0;
        info2[1] = 1.0;
        info2[3] = 1.0;
        info2[8] = 9.0;
        check_chordal_jacobians(
            Se2::new(1.0, -0.5, 0.8),
            Se2::new(2.5, 0.7, -2.0),
            Se2::new(0.9, 1.1, 0.4),
            info2,
        );
        let mut info3 = identity_info(6);
        info3[0] = 3.0;
        info3[4 * 6 + 4] = 7.0;
        check_chordal_jacobians(
            Se3::new(
                DQuat::from_euler(glam::EulerRot::XYZ, 0.3, -0.5, 1.2),
                DVec3::new(1.0, 2.0, -0.5),
            ),
            Se3::new(
                DQuat::from_euler(glam::EulerRot::XYZ, -0.7, 0.2, 2.0),
                DVec3::new(-1.0, 0.4, 0.9),
            ),
            Se3::new(
                DQuat::from_euler(glam::EulerRot::XYZ, 0.1, 0.9, -0.3),
                DVec3::new(0.3, -0.2, 0.1),
            ),
            info3,
        );
    }

    #[test]
    fn bad_edges_are_rejected() {
        let mut g = PoseGraph2::new();
        g.add_vertex(0, Se2::IDENTITY).unwrap();
        g.add_vertex(1, Se2::IDENTITY).unwrap();
        assert!(matches!(
            g.add_vertex(1, Se2::IDENTITY),
            Err(GraphError::DuplicateVertex(1))
        ));
        let bad = vec![1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 1.0];
        assert!(matches!(
            g.add_edge(0, 1, Se2::IDENTITY, bad),
            Err(GraphError::InformationNotPositiveDefinite { .. })
        ));
        assert!(g.add_edge(0, 7, Se2::IDENTITY, vec![1.0; 9]).is_err());
        assert!(g
            .add_edge(0, 1, Se2::new(f64::NAN, 0.0, 0.0), identity_info(3))
            .is_err());
        g.add_vertex(2, Se2::IDENTITY).unwrap();
        g.add_edge(0, 1, Se2::new(1.0, 0.0, 0.0), identity_info(3))
            .unwrap();
        assert!(matches!(
            g.check_connected(),
            Err(GraphError::Disconnected { vertex: 2 })
        ));
        assert!(g.optimize(&SolverOptions::default()).is_err());
    }

    fn identity_info(d: usize) -> Vec<f64> {
        let mut m = vec![0.0; d * d];
        for k in 0..d {
            m[k * d + k] = 1.0;
        }
        m
    }
}
