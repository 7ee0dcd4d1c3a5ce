//! Camera trajectories through a scene's free area, as continuous functions of time
//! returning `world_from_camera` (world z up; camera x right, y down, z forward).
//!
//! * Handheld: a Catmull-Rom spline through random waypoints (position, yaw, pitch),
//!   traversed at constant speed along its arc length, with hand tremor; `slow` and `fast`
//!   variants differ in speed and rotation rate.
//! * Loop: a closed spline around the free area, traversed exactly once over the duration, so
//!   the last pose equals the first (loop closure).
//! * Walking (head or chest camera, thesis ch. 3): forward speed from the step frequency,
//!   `V = alpha * f^beta * H` (eq. 3.11, alpha 0.2896, beta 1.7544), vertical oscillation of
//!   the body at the step frequency, lateral sway at half of it, a pace schedule with changes
//!   and stops, and optional stairs (height gained step by step).
//! * Robot: planar motion (SE(2)) at constant height along a closed smooth path.

use std::f64::consts::{PI, TAU};

use glam::{DMat3, DQuat, DVec3};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;

use super::scene::{FreeArea, Scene};
use super::SynthError;
use crate::geometry::Se3;
use crate::trajectory::TimedPose;

/// Names accepted by [`TrajectoryKind::from_name`].
pub const TRAJECTORIES: &[&str] = &[
    "handheld",
    "slow",
    "fast",
    "loop",
    "walk-head",
    "walk-chest",
    "stairs",
    "robot",
];

/// The kinds of trajectory.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum TrajectoryKind {
    /// Handheld spline at 0.35 m/s, moderate rotation.
    Handheld,
    /// Handheld at 0.12 m/s, slow rotation.
    Slow,
    /// Handheld at 0.9 m/s, fast rotation and stronger tremor.
    Fast,
    /// Closed loop around the room, returning exactly to its start.
    Loop,
    /// Walking person, head-mounted camera.
    WalkHead,
    /// Walking person, chest-mounted camera.
    WalkChest,
    /// Walking person (head camera) climbing a flight of stairs halfway.
    Stairs,
    /// Planar robot, camera 0.4 m above the floor.
    Robot,
}

impl TrajectoryKind {
    /// Parses a name from [`TRAJECTORIES`].
    pub fn from_name(name: &str) -> Result<TrajectoryKind, SynthError> {
        Ok(match name {
            "handheld" => TrajectoryKind::Handheld,
            "slow" => TrajectoryKind::Slow,
            "fast" => TrajectoryKind::Fast,
            "loop" => TrajectoryKind::Loop,
            "walk-head" | "walking" | "walk" => TrajectoryKind::WalkHead,
            "walk-chest" => TrajectoryKind::WalkChest,
            "stairs" => TrajectoryKind::Stairs,
            "robot" => TrajectoryKind::Robot,
            _ => {
                return Err(SynthError::UnknownTrajectory {
                    name: name.into(),
                    known: TRAJECTORIES.join(", "),
                });
            }
        })
    }
}

/// Where the walking person wears the camera.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum Mount {
    /// On the head (eye height 0.93 H, head turns).
    Head,
    /// On the chest (0.72 H, follows the torso).
    Chest,
}

/// One segment of a walking schedule.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PaceSegment {
    /// Duration, seconds.
    pub duration: f64,
    /// Step frequency, steps per second (0 = standing still).
    pub frequency: f64,
}

/// Parameters of the walking model.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct WalkingParams {
    /// Height of the person, metres.
    pub height: f64,
    /// alpha of `V = alpha f^beta H`.
    pub alpha: f64,
    /// beta of `V = alpha f^beta H`.
    pub beta: f64,
    /// Camera mount.
    pub mount: Mount,
    /// Pace schedule (repeated when the duration is longer); transitions are smoothed over
    /// `transition` seconds.
    pub schedule: Vec<PaceSegment>,
    /// Smoothing of frequency changes, seconds.
    pub transition: f64,
    /// Peak vertical oscillation of the body at a nominal 1.8 steps/s, metres.
    pub bob_amplitude: f64,
    /// Peak lateral sway, metres.
    pub sway_amplitude: f64,
    /// Stairs: `(start time s, number of steps, rise per step m)`; the person climbs one
    /// riser per step from the start time on.
    pub stairs: Option<(f64, usize, f64)>,
    /// Peak vertical oscillation at the stride frequency (half the step frequency) while
    /// climbing the stairs, metres: the legs lift the body unequally from one riser to the
    /// next. 0 = both legs alike (absent in older files).
    #[serde(default)]
    pub stride_bob: f64,
}

impl Default for WalkingParams {
    fn default() -> Self {
        WalkingParams {
            height: 1.75,
            alpha: 0.2896,
            beta: 1.7544,
            mount: Mount::Head,
            schedule: vec![
                PaceSegment {
                    duration: 6.0,
                    frequency: 1.6,
                },
                PaceSegment {
                    duration: 5.0,
                    frequency: 2.0,
                },
                PaceSegment {
                    duration: 2.0,
                    frequency: 0.0,
                },
                PaceSegment {
                    duration: 6.0,
                    frequency: 1.3,
                },
            ],
            transition: 0.8,
            bob_amplitude: 0.025,
            sway_amplitude: 0.02,
            stairs: None,
            stride_bob: 0.0,
        }
    }
}

impl WalkingParams {
    /// Forward speed (m/s) at step frequency `f` (thesis eq. 3.11).
    pub fn speed(&self, f: f64) -> f64 {
        if f <= 0.0 {
            0.0
        } else {
            self.alpha * f.powf(self.beta) * self.height
        }
    }

    /// The (smoothed) step frequency at time `t`.
    pub fn frequency_at(&self, t: f64) -> f64 {
        let total: f64 = self.schedule.iter().map(|s| s.duration.max(0.0)).sum();
        if self.schedule.is_empty() || total <= 0.0 {
            return 0.0;
        }
        let tt = t.rem_euclid(total);
        let mut acc = 0.0;
        let n = self.schedule.len();
        for (k, seg) in self.schedule.iter().enumerate() {
            let end = acc + seg.duration.max(0.0);
            if tt < end || k == n - 1 {
                // Smooth the change from the previous segment over `transition` seconds.
                let prev = self.schedule[(k + n - 1) % n].frequency;
                let since = tt - acc;
                let tr = self.transition.max(1e-6);
                if since < tr && (t >= tr || k > 0) {
                    let a = 0.5 - 0.5 * (PI * since / tr).cos();
                    return prev + (seg.frequency - prev) * a;
                }
                return seg.frequency;
            }
            acc = end;
        }
        0.0
    }
}

/// A closed or open Catmull-Rom spline over `[x, y, z, yaw, pitch]` control points,
/// parametrised by arc length of the position.
#[derive(Clone, Debug)]
struct Spline {
    points: Vec<[f64; 5]>,
    closed: bool,
    /// (parameter, cumulative length) table.
    table: Vec<(f64, f64)>,
}

impl Spline {
    fn new(points: Vec<[f64; 5]>, closed: bool) -> Spline {
        let mut s = Spline {
            points,
            closed,
            table: Vec::new(),
        };
        let segs = s.segments();
        let per = 200;
        let mut acc = 0.0;
        let mut prev = s.eval(0.0);
        s.table.push((0.0, 0.0));
        for i in 1..=segs * per {
            let u = i as f64 / per as f64;
            let p = s.eval(u);
            acc += ((p[0] - prev[0]).powi(2) + (p[1] - prev[1]).powi(2) + (p[2] - prev[2]).powi(2))
                .sqrt();
            s.table.push((u, acc));
            prev = p;
        }
        s
    }

    fn segments(&self) -> usize {
        if self.closed {
            self.points.len()
        } else {
            self.points.len().saturating_sub(1).max(1)
        }
    }

    fn length(&self) -> f64 {
        self.table.last().map_or(0.0, |t| t.1)
    }

    /// Control point `i` (any integer): wrapped for closed splines (yaw continued by 2 pi per
    /// lap), clamped for open ones.
    fn point(&self, i: i64) -> [f64; 5] {
        let n = self.points.len() as i64;
        if self.closed {
            let lap = i.div_euclid(n);
            let mut p = self.points[i.rem_euclid(n) as usize];
            p[3] += TAU * lap as f64;
            p
        } else {
            self.points[i.clamp(0, n - 1) as usize]
        }
    }

    fn eval(&self, u: f64) -> [f64; 5] {
        let segs = self.segments() as f64;
        let u = u.clamp(0.0, segs);
        let i = (u.floor() as i64).min(segs as i64 - 1);
        let t = u - i as f64;
        let (p0, p1, p2, p3) = (
            self.point(i - 1),
            self.point(i),
            self.point(i + 1),
            self.point(i + 2),
        );
        let t2 = t * t;
        let t3 = t2 * t;
        let mut out = [0.0; 5];
        for k in 0..5 {
            out[k] = 0.5
                * (2.0 * p1[k]
                    + (-p0[k] + p2[k]) * t
                    + (2.0 * p0[k] - 5.0 * p1[k] + 4.0 * p2[k] - p3[k]) * t2
                    + (-p0[k] + 3.0 * p1[k] - 3.0 * p2[k] + p3[k]) * t3);
        }
        out
    }

    /// Point at arc length `s` (clamped; wrapped for closed splines).
    fn at_length(&self, s: f64) -> [f64; 5] {
        let len = self.length();
        let s = if self.closed && len > 0.0 {
            s.rem_euclid(len)
        } else {
            s.clamp(0.0, len)
        };
        let k = self.table.partition_point(|e| e.1 < s);
        let u = if k == 0 {
            0.0
        } else if k >= self.table.len() {
            self.table[self.table.len() - 1].0
        } else {
            let (u0, s0) = self.table[k - 1];
            let (u1, s1) = self.table[k];
            u0 + (u1 - u0) * if s1 > s0 { (s - s0) / (s1 - s0) } else { 0.0 }
        };
        self.eval(u)
    }

    /// Heading (yaw of the tangent) at arc length `s`.
    fn heading_at(&self, s: f64) -> f64 {
        let a = self.at_length(s - 0.05);
        let b = self.at_length(s + 0.05);
        (b[1] - a[1]).atan2(b[0] - a[0])
    }
}

/// Smooth pseudo-random jitter: a sum of sinusoids with fixed random phases.
#[derive(Clone, Debug)]
struct Jitter {
    terms: Vec<(f64, f64, f64)>, // (amplitude, frequency, phase)
}

impl Jitter {
    fn new(rng: &mut Pcg64, amplitude: f64, freqs: &[f64]) -> Jitter {
        let terms = freqs
            .iter()
            .map(|&f| {
                (
                    amplitude / freqs.len() as f64 * 1.6,
                    f,
                    rng.random_range(0.0..TAU),
                )
            })
            .collect();
        Jitter { terms }
    }
    fn at(&self, x: f64) -> f64 {
        self.terms
            .iter()
            .map(|(a, f, p)| a * (TAU * f * x + p).sin())
            .sum()
    }
}

/// `world_from_camera` of a camera at `eye` with the given yaw (about world z, 0 = looking
/// along +x), pitch (up positive) and roll (about the viewing direction).
pub fn camera_pose(eye: DVec3, yaw: f64, pitch: f64, roll: f64) -> Se3 {
    // Camera axes for yaw = pitch = roll = 0: z_c -> +x_w, x_c -> -y_w, y_c -> -z_w.
    let base = DMat3::from_cols(
        DVec3::new(0.0, -1.0, 0.0),
        DVec3::new(0.0, 0.0, -1.0),
        DVec3::new(1.0, 0.0, 0.0),
    );
    let r = DMat3::from_rotation_z(yaw)
        * DMat3::from_rotation_y(-pitch)
        * DMat3::from_rotation_x(roll)
        * base;
    Se3::new(DQuat::from_mat3(&r), eye)
}

#[derive(Clone, Debug)]
enum Motion {
    Handheld {
        spline: Spline,
        speed: f64,
        jitter: [Jitter; 6],
    },
    Loop {
        spline: Spline,
        jitter: [Jitter; 6],
    },
    Walk {
        path: Spline,
        params: WalkingParams,
        /// `(distance walked, step phase, body heading)` every `dt` seconds.
        table: Vec<(f64, f64, f64)>,
        dt: f64,
        head: [Jitter; 2],
    },
    Robot {
        path: Spline,
        speed: f64,
    },
}

/// A camera trajectory: `world_from_camera` as a function of time over `[0, duration]`.
#[derive(Clone, Debug)]
pub struct Trajectory {
    kind: TrajectoryKind,
    duration: f64,
    motion: Motion,
}

fn ellipse_points(
    area: &FreeArea,
    n: usize,
    shrink: f64,
    rng: &mut Pcg64,
    z: (f64, f64),
    outward: bool,
) -> Vec<[f64; 5]> {
    let c = area.center();
    let e = area.extent() * 0.5 * shrink;
    (0..n)
        .map(|k| {
            let th = TAU * k as f64 / n as f64;
            let r = rng.random_range(0.8..1.0);
            let x = c.x + e.x * r * th.cos();
            let y = c.y + e.y * r * th.sin();
            let yaw = if outward {
                th + rng.random_range(-0.5..0.5)
            } else {
                th + PI * 0.5
            };
            let height = if z.1 > z.0 {
                rng.random_range(z.0..z.1)
            } else {
                z.0
            };
            [x, y, height, yaw, rng.random_range(-0.3..0.05)]
        })
        .collect()
}

/// Fastest turn of a walker's body, rad/s (about 150 degrees per second: a person turning
/// round takes over a second).
const MAX_TURN_RATE: f64 = 2.6;

/// `(distance, phase, heading)` at time `t` from a walk's table (linear between entries;
/// headings are unwrapped, so the interpolation is continuous).
fn interpolate(table: &[(f64, f64, f64)], dt: f64, t: f64) -> (f64, f64, f64) {
    let x = (t.max(0.0) / dt).min((table.len() - 1) as f64);
    let i = (x.floor() as usize).min(table.len().saturating_sub(2));
    let a = x - i as f64;
    let (s0, p0, h0) = table[i];
    let (s1, p1, h1) = table[(i + 1).min(table.len() - 1)];
    (s0 + (s1 - s0) * a, p0 + (p1 - p0) * a, h0 + (h1 - h0) * a)
}

impl Trajectory {
    /// A trajectory of `kind` through `scene`'s free area lasting `duration` seconds.
    pub fn new(
        kind: TrajectoryKind,
        scene: &Scene,
        duration: f64,
        seed: u64,
    ) -> Result<Trajectory, SynthError> {
        if !(duration.is_finite() && duration > 0.0) {
            return Err(SynthError::InvalidParameter {
                name: "duration",
                why: format!("{duration} s must be > 0"),
            });
        }
        let area = scene.free_area();
        let mut rng = Pcg64::seed_from_u64(seed ^ 0x7a3c_0000_0000_0001);
        let eye = (
            1.3f64.min(area.ceiling - 0.5),
            1.6f64.min(area.ceiling - 0.3),
        );
        let motion = match kind {
            TrajectoryKind::Handheld | TrajectoryKind::Slow | TrajectoryKind::Fast => {
                let (speed, yaw_rate, tremor) = match kind {
                    TrajectoryKind::Slow => (0.12, 0.15, 0.002),
                    TrajectoryKind::Fast => (0.9, 0.9, 0.008),
                    _ => (0.35, 0.4, 0.004),
                };
                // Waypoints spaced ~1 m; yaw drifts by yaw_rate rad/s between them.
                let length = speed * duration;
                let n = ((length / 1.0).ceil() as usize + 1).max(4);
                let seg_time = duration / (n - 1) as f64;
                let mut yaw = rng.random_range(0.0..TAU);
                let mut pts = Vec::with_capacity(n);
                let (mut x, mut y) = (area.center().x, area.center().y);
                for _ in 0..n {
                    pts.push([
                        x,
                        y,
                        rng.random_range(eye.0..eye.1),
                        yaw,
                        rng.random_range(-0.35..0.05),
                    ]);
                    let step = speed * seg_time;
                    let dir = rng.random_range(0.0..TAU);
                    x = (x + step * dir.cos()).clamp(area.min.x, area.max.x);
                    y = (y + step * dir.sin()).clamp(area.min.y, area.max.y);
                    yaw += rng.random_range(-1.0..1.0) * yaw_rate * seg_time;
                }
                let spline = Spline::new(pts, false);
                let sp = spline.length() / duration;
                let fr = [1.3, 2.9, 4.7];
                let jitter = [
                    Jitter::new(&mut rng, tremor, &fr),
                    Jitter::new(&mut rng, tremor, &fr),
                    Jitter::new(&mut rng, tremor, &fr),
                    Jitter::new(&mut rng, tremor * 2.0, &fr),
                    Jitter::new(&mut rng, tremor * 2.0, &fr),
                    Jitter::new(&mut rng, tremor * 2.0, &fr),
                ];
                Motion::Handheld {
                    spline,
                    speed: sp,
                    jitter,
                }
            }
            TrajectoryKind::Loop => {
                let pts = ellipse_points(&area, 8, 0.9, &mut rng, eye, true);
                let spline = Spline::new(pts, true);
                // Integer frequencies per lap keep the jitter periodic.
                let fr = [3.0, 7.0, 13.0];
                let jitter = [
                    Jitter::new(&mut rng, 0.004, &fr),
                    Jitter::new(&mut rng, 0.004, &fr),
                    Jitter::new(&mut rng, 0.004, &fr),
                    Jitter::new(&mut rng, 0.01, &fr),
                    Jitter::new(&mut rng, 0.01, &fr),
                    Jitter::new(&mut rng, 0.01, &fr),
                ];
                Motion::Loop { spline, jitter }
            }
            TrajectoryKind::WalkHead | TrajectoryKind::WalkChest | TrajectoryKind::Stairs => {
                let mut params = WalkingParams {
                    mount: if kind == TrajectoryKind::WalkChest {
                        Mount::Chest
                    } else {
                        Mount::Head
                    },
                    ..WalkingParams::default()
                };
                let staircase = scene.params().staircase;
                if kind == TrajectoryKind::Stairs {
                    params.stairs = Some((duration * 0.3, 12, 0.17));
                    // On a scene's staircase the pace puts one step on each tread:
                    // alpha f^beta H / f = run.
                    let frequency = match staircase {
                        Some(st) if params.beta > 1.0 => (st.run / (params.alpha * params.height))
                            .powf(1.0 / (params.beta - 1.0)),
                        _ => 1.5,
                    };
                    params.schedule = vec![PaceSegment {
                        duration: 1e9,
                        frequency,
                    }];
                }
                let traj = Trajectory::walking(scene, params, duration, seed);
                if let Motion::Walk { path, table, .. } = &traj.motion {
                    let end = table.last().map_or(0.0, |e| e.0);
                    if scene.params().open_route && end > path.length() {
                        return Err(SynthError::InvalidParameter {
                            name: "duration",
                            why: format!(
                                "a {duration} s walk covers {end:.1} m, longer than the {:.1} m \
                                 route through `{}`",
                                path.length(),
                                scene.params().name
                            ),
                        });
                    }
                    let reach = path.at_length(end)[0];
                    if let Some(st) = staircase.filter(|_| kind != TrajectoryKind::Stairs) {
                        if reach > st.first_riser_x - 0.5 {
                            return Err(SynthError::InvalidParameter {
                                name: "trajectory",
                                why: format!(
                                    "a {duration} s walk reaches the staircase of `{}` at x = \
                                     {:.1} m; only the `stairs` trajectory climbs it",
                                    scene.params().name,
                                    st.first_riser_x
                                ),
                            });
                        }
                    }
                }
                return Ok(traj);
            }
            TrajectoryKind::Robot => {
                let pts = ellipse_points(&area, 6, 0.8, &mut rng, (0.4, 0.4), false);
                let spline = Spline::new(pts, true);
                Motion::Robot {
                    path: spline,
                    speed: 0.3,
                }
            }
        };
        Ok(Trajectory {
            kind,
            duration,
            motion,
        })
    }

    /// A walking trajectory with explicit parameters (head or chest mount, schedule, stairs)
    /// along a closed path around the free area.
    /// ([`crate::synth::SceneParams::open_route`]: along the scene's length instead). On a
    /// scene with a staircase, `params.stairs` keeps only its presence: the climb starts when
    /// the walker is half a tread before the first riser, with the scene's risers.
    pub fn walking(
        scene: &Scene,
        mut params: WalkingParams,
        duration: f64,
        seed: u64,
    ) -> Trajectory {
        let area = scene.free_area();
        let mut rng = Pcg64::seed_from_u64(seed ^ 0x3a1c_0000_0000_0003);
        let open = scene.params().open_route;
        let path = if open {
            // Straight along x with a gentle weave across the free width, so the heading is
            // not constant.
            let c = area.center();
            let amp = (0.4 * area.extent().y).min(0.3);
            let phase = rng.random_range(0.0..TAU);
            let (x0, x1) = (area.min.x + 0.3, area.max.x - 0.3);
            let n = ((x1 - x0) / 4.0).ceil().max(1.0) as usize;
            let pts = (0..=n)
                .map(|k| {
                    let x = x0 + (x1 - x0) * k as f64 / n as f64;
                    [x, c.y + amp * (TAU * x / 14.0 + phase).sin(), 0.0, 0.0, 0.0]
                })
                .collect();
            Spline::new(pts, false)
        } else {
            let pts = ellipse_points(&area, 8, 0.85, &mut rng, (0.0, 0.0), false);
            Spline::new(pts, true)
        };
        // Integrate distance and step phase on a fine grid.
        let dt = 1e-3;
        let n = (duration.max(0.0) / dt).ceil() as usize + 2;
        let mut table = Vec::with_capacity(n);
        // Start where the loop is straightest, facing along it: a walk that began in the
        // turn at the tip of a corridor's narrow loop would start with a spin.
        let len = path.length();
        let bend = |s: f64| {
            ((path.heading_at(s + 0.5) - path.heading_at(s - 0.5) + PI).rem_euclid(TAU) - PI).abs()
        };
        let start = if open {
            0.0
        } else {
            (0..(len / 0.1).ceil().max(1.0) as usize)
                .map(|k| k as f64 * 0.1)
                .min_by(|a, b| bend(*a).total_cmp(&bend(*b)))
                .unwrap_or(0.0)
        };
        let (mut s, mut phase) = (start, 0.0);
        let mut heading = path.heading_at(start);
        for i in 0..n {
            table.push((s, phase, heading));
            let t = (i as f64 + 0.5) * dt;
            let f = params.frequency_at(t);
            s += params.speed(f) * dt;
            phase += f * dt;
            // The body turns towards the path's tangent no faster than a person does: where
            // the path doubles back (the tip of a corridor's narrow loop) the tangent swings
            // by up to 180 degrees within a few centimetres.
            let turn = (path.heading_at(s) - heading + PI).rem_euclid(TAU) - PI;
            heading += turn.clamp(-MAX_TURN_RATE * dt, MAX_TURN_RATE * dt);
        }
        if let (Some(st), Some(_)) = (scene.params().staircase, params.stairs) {
            let x = st.first_riser_x - 0.5 * st.run;
            let i = table
                .iter()
                .position(|e| path.at_length(e.0)[0] >= x)
                .unwrap_or(table.len());
            params.stairs = Some((i as f64 * dt, st.steps, st.rise));
        }
        let head = [
            Jitter::new(&mut rng, 0.25, &[0.07, 0.13]),
            Jitter::new(&mut rng, 0.08, &[0.05, 0.11]),
        ];
        let kind = if params.stairs.is_some() {
            TrajectoryKind::Stairs
        } else if params.mount == Mount::Chest {
            TrajectoryKind::WalkChest
        } else {
            TrajectoryKind::WalkHead
        };
        Trajectory {
            kind,
            duration,
            motion: Motion::Walk {
                path,
                params,
                table,
                dt,
                head,
            },
        }
    }

    /// The kind.
    pub fn kind(&self) -> TrajectoryKind {
        self.kind
    }
    /// Duration, seconds.
    pub fn duration(&self) -> f64 {
        self.duration
    }

    /// For walking trajectories: (distance walked m, step phase in steps) at time `t`.
    pub fn walking_state(&self, t: f64) -> Option<(f64, f64)> {
        match &self.motion {
            Motion::Walk { table, dt, .. } => {
                let (s, phase, _) = interpolate(table, *dt, t);
                Some((s - table[0].0, phase))
            }
            _ => None,
        }
    }

    /// `world_from_camera` at time `t` seconds (clamped to `[0, duration]`; a `loop` repeats its
    /// lap after `duration`).
    pub fn pose_at(&self, t: f64) -> Se3 {
        // A closed loop goes on lap after lap past its duration (one lap); the others stop.
        let t = if matches!(self.motion, Motion::Loop { .. }) {
            t.max(0.0)
        } else {
            t.clamp(0.0, self.duration)
        };
        match &self.motion {
            Motion::Handheld {
                spline,
                speed,
                jitter,
            } => {
                let p = spline.at_length(speed * t);
                let j: Vec<f64> = jitter.iter().map(|j| j.at(t)).collect();
                camera_pose(
                    DVec3::new(p[0] + j[0], p[1] + j[1], p[2] + j[2]),
                    p[3] + j[3],
                    p[4] + j[4],
                    j[5],
                )
            }
            Motion::Loop { spline, jitter } => {
                let phase = t / self.duration;
                let p = spline.at_length(phase * spline.length());
                let j: Vec<f64> = jitter.iter().map(|j| j.at(phase)).collect();
                camera_pose(
                    DVec3::new(p[0] + j[0], p[1] + j[1], p[2] + j[2]),
                    p[3] + j[3],
                    p[4] + j[4],
                    j[5],
                )
            }
            Motion::Robot { path, speed } => {
                let s = speed * t;
                let p = path.at_length(s);
                camera_pose(DVec3::new(p[0], p[1], 0.4), path.heading_at(s), 0.0, 0.0)
            }
            Motion::Walk {
                path,
                params,
                head,
                table,
                dt,
            } => {
                let (s, phase, heading) = interpolate(table, *dt, t);
                let p = path.at_length(s);
                let f = params.frequency_at(t);
                let v = params.speed(f);
                let walking = (v / params.speed(1.8).max(1e-9)).clamp(0.0, 1.3);
                let bob = params.bob_amplitude * walking * (TAU * phase).cos();
                let sway = params.sway_amplitude * walking * (PI * phase).sin();
                let lateral = DVec3::new(-heading.sin(), heading.cos(), 0.0);
                let (height, yaw_look, pitch) = match params.mount {
                    Mount::Head => (0.93 * params.height, head[0].at(t), -0.1 + head[1].at(t)),
                    Mount::Chest => (
                        0.72 * params.height,
                        0.05 * (PI * phase).sin() * walking,
                        -0.05,
                    ),
                };
                let mut z = height + bob;
                if let Some((start, steps, rise)) = params.stairs {
                    if t > start {
                        let (_, p0) = self.walking_state(start).unwrap_or((0.0, 0.0));
                        let climbed = (phase - p0).clamp(0.0, steps as f64);
                        // One riser per step, smoothed within the step.
                        let k = climbed.floor();
                        let frac = climbed - k;
                        z += rise * (k + 0.5 - 0.5 * (PI * frac).cos());
                        if climbed < steps as f64 {
                            z += params.stride_bob * (PI * climbed).sin();
                        }
                    }
                }
                let roll = 0.02 * walking * (PI * phase).sin();
                let eye = DVec3::new(p[0], p[1], z) + lateral * sway;
                camera_pose(eye, heading + yaw_look, pitch, roll)
            }
        }
    }

    /// `frames` poses at `fps` frames per second starting at `t0`.
    pub fn sample(&self, frames: usize, fps: f64, t0: f64) -> Vec<TimedPose> {
        (0..frames)
            .map(|i| {
                let t = i as f64 / fps;
                TimedPose {
                    timestamp: t0 + t,
                    world_from_camera: self.pose_at(t),
                }
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn camera_pose_axes() {
        let p = camera_pose(DVec3::ZERO, 0.0, 0.0, 0.0);
        assert!((p.transform_vector(DVec3::Z) - DVec3::X).length() < 1e-12);
        assert!((p.transform_vector(DVec3::Y) + DVec3::Z).length() < 1e-12);
        let p = camera_pose(DVec3::ZERO, PI / 2.0, 0.3, 0.0);
        let f = p.transform_vector(DVec3::Z);
        assert!((f - DVec3::new(0.0, 0.3f64.cos(), 0.3f64.sin())).length() < 1e-12);
    }

    #[test]
    fn hall_walk_never_returns_and_stairwell_walk_climbs_the_treads() {
        let hall = Scene::preset("hall", 7).unwrap();
        let t = Trajectory::new(TrajectoryKind::WalkHead, &hall, 60.0, 7).unwrap();
        let pos: Vec<DVec3> = (0..=600)
            .map(|i| t.pose_at(i as f64 * 0.1).translation)
            .collect();
        assert!(t.walking_state(60.0).unwrap().0 > 60.0);
        for (i, a) in pos.iter().enumerate() {
            for b in pos.iter().skip(i + 100) {
                assert!(
                    (a.truncate() - b.truncate()).length() > 2.0,
                    "the hall walk comes back to {a} 10 s or more later"
                );
            }
        }
        // Longer than the route, or a flat walk into the stairs: refused.
        assert!(Trajectory::new(TrajectoryKind::WalkHead, &hall, 100.0, 7).is_err());
        let well = Scene::preset("stairwell", 7).unwrap();
        let st = well.params().staircase.unwrap();
        assert!(Trajectory::new(TrajectoryKind::WalkHead, &well, 60.0, 7).is_err());
        let t = Trajectory::new(TrajectoryKind::Stairs, &well, 60.0, 7).unwrap();
        // The eye stays at its height over the tread under it, within half a riser (where the
        // foot is between two treads) and the bob.
        let eye = 0.93 * WalkingParams::default().height;
        let mut worst = 0.0f64;
        for i in 0..=600 {
            let p = t.pose_at(i as f64 * 0.1).translation;
            worst = worst.max((p.z - st.floor_height(p.x) - eye).abs());
        }
        assert!(
            worst < 0.5 * st.rise + 0.05,
            "eye off the treads by {worst} m"
        );
        let end = t.pose_at(60.0).translation;
        assert!((end.z - eye - st.height()).abs() < 0.05, "{end}");
    }

    #[test]
    fn walking_speed_follows_step_frequency() {
        let p = WalkingParams::default();
        let v = p.speed(1.8);
        assert!((v - 0.2896 * 1.8f64.powf(1.7544) * 1.75).abs() < 1e-12);
        assert_eq!(p.speed(0.0), 0.0);
        assert!((p.frequency_at(3.0) - 1.6).abs() < 1e-12);
        assert!((p.frequency_at(8.0) - 2.0).abs() < 1e-12);
        assert_eq!(p.frequency_at(12.0), 0.0);
    }
}
