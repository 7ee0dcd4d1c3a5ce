//! Incremental and multi-level optimisation for a SLAM back-end (thesis 6.4.5).
//!
//! [`IncrementalPoseGraph`] keeps the solver problem alive: new vertices and edges are appended
//! to it and re-optimisation starts from the current estimate (only the sparsity analysis is
//! redone when the structure grew). [`optimize_multilevel`] first optimises the keyframes with
//! keyframe-to-keyframe edges, then the other vertices with the keyframes fixed.

use super::pose_graph::{Pose, PoseGraph};
use super::solver::{Problem, SolveReport, SolverOptions};
use super::GraphError;

/// A pose graph that grows and is re-optimised in place.
pub struct IncrementalPoseGraph<P: Pose> {
    graph: PoseGraph<P>,
    problem: Problem<P>,
    edges_in_problem: usize,
}

impl<P: Pose> Default for IncrementalPoseGraph<P> {
    fn default() -> Self {
        Self::new()
    }
}

impl<P: Pose> IncrementalPoseGraph<P> {
    /// An empty graph. The first vertex added is the gauge (fixed).
    pub fn new() -> Self {
        IncrementalPoseGraph {
            graph: PoseGraph::new(),
            problem: Problem::new(),
            edges_in_problem: 0,
        }
    }
    /// Adds a vertex with its initial `world_from_body` pose.
    pub fn add_vertex(&mut self, id: i64, pose: P) -> Result<usize, GraphError> {
        let k = self.graph.add_vertex(id, pose)?;
        let v = self.problem.add_variable(pose);
        if v == 0 {
            self.problem.set_fixed(0, true);
        }
        Ok(k)
    }
    /// Adds a relative-pose edge `from_from_to` with its information matrix.
    pub fn add_edge(
        &mut self,
        from_id: i64,
        to_id: i64,
        measurement: P,
        information: Vec<f64>,
    ) -> Result<usize, GraphError> {
        self.graph
            .add_edge(from_id, to_id, measurement, information)
    }
    /// Re-optimises from the current estimate.
    pub fn optimize(&mut self, opts: &SolverOptions) -> Result<SolveReport, GraphError> {
        self.graph.check_connected()?;
        while self.edges_in_problem < self.graph.edges.len() {
            let f = self.graph.edge_factor(self.edges_in_problem)?;
            self.problem.add_factor(f)?;
            self.edges_in_problem += 1;
        }
        let rep = self.problem.optimize(opts)?;
        self.graph.poses.clone_from(&self.problem.values);
        Ok(rep)
    }
    /// Current pose of vertex `id`.
    pub fn pose(&self, id: i64) -> Option<P> {
        self.graph.index_of(id).map(|k| self.problem.values[k])
    }
    /// The underlying graph (poses as of the last optimisation).
    pub fn graph(&self) -> &PoseGraph<P> {
        &self.graph
    }
}

/// Two-level optimisation: (1) keyframes only, with edges between keyframes; (2) all other
/// vertices with keyframes fixed, using every edge. `is_keyframe[k]` marks vertex index `k`.
/// Returns the reports of both levels.
pub fn optimize_multilevel<P: Pose>(
    g: &mut PoseGraph<P>,
    is_keyframe: &[bool],
    opts: &SolverOptions,
) -> Result<(SolveReport, SolveReport), GraphError> {
    if is_keyframe.len() != g.poses.len() {
        return Err(GraphError::Invalid(
            "keyframe mask length differs from the vertex count".into(),
        ));
    }
    let mut sub = PoseGraph::<P>::new();
    let mut map = vec![usize::MAX; g.poses.len()];
    for (k, &kf) in is_keyframe.iter().enumerate() {
        if kf {
            map[k] = sub.add_vertex(g.ids[k], g.poses[k])?;
            sub.fixed[map[k]] = g.fixed[k];
        }
    }
    for e in &g.edges {
        if is_keyframe[e.from] && is_keyframe[e.to] {
            sub.add_edge_by_index(map[e.from], map[e.to], e.measurement, e.information.clone())?;
        }
    }
    let level1 = sub.optimize(opts)?;
    for (k, &m) in map.iter().enumerate() {
        if m != usize::MAX {
            g.poses[k] = sub.poses[m];
        }
    }
    g.check_connected()?;
    let mut p: Problem<P> = g.to_problem()?;
    for (k, &kf) in is_keyframe.iter().enumerate() {
        if kf {
            p.set_fixed(k, true);
        }
    }
    let level2 = p.optimize(opts)?;
    g.poses = p.values;
    Ok((level1, level2))
}
