//! The SLAM system: the front-end on the caller's thread, the back-end on its own thread
//! behind a bounded keyframe queue.

use std::sync::mpsc::{channel, sync_channel, Receiver, Sender, SyncSender};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::Instant;

use super::backend::{
    loop_record_bytes, Backend, KeyframeTiming, LoopRecord, Relocalisation, Shared,
};
use super::events::{EventHub, EventOptions, SlamEvent, SlamEvents};
use super::fusion::KeyframeFuser;
use super::keyframe::{Keyframe, KeyframeLink};
use super::map::Map;
use super::memory::{vec_bytes, MemoryBreakdown, MemoryReport};
use super::{information_from, BufferedFusion, FrameEdges, SlamConfig, SlamError};
use crate::camera::PinholeCamera;
use crate::geometry::{Covariance6, Se3};
use crate::gpu::ComputeBackend;
use crate::graph::{PoseGraph3, SolverOptions};
use crate::image::{ColourImage, ImageF32, RgbdFrame};
use crate::odometry::{GeometricParam, Odometry, StageTimes};
use crate::place::Vocabulary;
use crate::trajectory::TimedPose;

/// Tracking state of a frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FrameStatus {
    /// Tracked against the reference.
    Tracking,
    /// Tracked, and it started a new keyframe.
    NewKeyframe,
    /// Not tracked: tracking was lost and relocalisation has not succeeded (no pose).
    Lost,
    /// Relocalised against the keyframe database on this frame.
    Relocalised,
}

/// Per-frame record kept for the final optimisation and outputs.
#[derive(Clone, Copy, Debug)]
pub struct FrameRecord {
    /// Frame index in the session.
    pub index: usize,
    /// Time stamp, seconds.
    pub timestamp: f64,
    /// Status.
    pub status: FrameStatus,
    /// Front-end (odometric) `world_from_camera`; `None` while lost.
    pub frontworld_from_camera: Option<Se3>,
    /// Keyframe the frame was tracked under and `keyframe_from_camera`.
    pub keyframe: Option<(usize, Se3)>,
    /// Front-end time of the frame, milliseconds.
    pub frontend_ms: f64,
    /// Odometry stage times.
    pub times: StageTimes,
    /// Fusion time, milliseconds.
    pub fusion_ms: f64,
    /// Covisibility with the odometry reference.
    pub covisibility: f64,
    /// Covisibility of the current keyframe with the frame.
    pub keyframe_covisibility: f64,
    /// Odometry diagnostics of the frame's alignment (0 where it was not tracked).
    pub diagnostics: OdometryDiagnostics,
    /// Covariance of the frame's alignment to its odometry reference (`ref_from_camera`,
    /// right perturbation in the camera frame, `[v; w]` in m and rad); `None` where it was
    /// not tracked or the alignment gave none.
    pub odometry_covariance: Option<Covariance6>,
    /// Covariance of [`Self::keyframe`]'s `keyframe_from_camera` composed along the odometry
    /// references since the keyframe (same convention); `None` where it was not tracked.
    pub keyframe_covariance: Option<Covariance6>,
}

/// What the odometry reported about one frame's alignment, for plots and failure analysis: a
/// converged photometric scale far above the recent frames' (10x was seen on a wrong
/// convergence) or an exploding condition number are the signs of a bad alignment.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct OdometryDiagnostics {
    /// Photometric residual scale at the finest level, intensity levels (0-255 scale).
    pub sigma_photo: f64,
    /// Geometric residual scale at the finest level, 1/m (or m with depth residuals).
    pub sigma_geo: f64,
    /// Student-t degrees of freedom at the finest level.
    pub nu: f64,
    /// Condition number of the final Hessian.
    pub condition_number: f64,
    /// Gauss-Newton iterations over all levels.
    pub iterations: usize,
    /// Whether this frame became the odometry's reference (the frames after it are aligned
    /// to it until the next switch).
    pub new_reference: bool,
}

/// What [`Slam::process`] returns for one frame.
#[derive(Clone, Copy, Debug)]
pub struct FrameReport {
    /// The frame's record.
    pub record: FrameRecord,
    /// Status.
    pub status: FrameStatus,
    /// `world_from_camera` corrected by the latest loop closures; `None` while lost.
    pub world_from_camera: Option<Se3>,
    /// Keyframes so far.
    pub keyframes: usize,
    /// Accepted loops so far.
    pub loops: usize,
}

/// Everything a finished run produced.
pub struct SlamResult {
    /// Per-frame records (front-end).
    pub frames: Vec<FrameRecord>,
    /// Final `world_from_camera` of every tracked frame (after the all-frames optimisation).
    pub trajectory: Vec<TimedPose>,
    /// Front-end (odometry-only) trajectory of the tracked frames.
    pub odometry: Vec<TimedPose>,
    /// Optimised `world_from_keyframe`, one per keyframe.
    pub keyframe_poses: Vec<Se3>,
    /// Loops found (accepted and rejected).
    pub loops: Vec<LoopRecord>,
    /// Back-end cost per keyframe of this session.
    pub timings: Vec<KeyframeTiming>,
    /// The map to save (keyframes, descriptors, graph).
    pub map: Map,
    /// Milliseconds of the final keyframe and all-frames optimisations.
    pub final_optimise_ms: f64,
    /// The instance's memory account at the end of the run (after the back-end stopped and
    /// freed its segmentation buffers), with its peak over the run (see [`Slam::memory`]).
    pub memory: MemoryReport,
}

enum ToBackend {
    Keyframe(Box<Keyframe>),
    Relocalise(
        Box<RgbdFrame>,
        Sender<Result<Option<Relocalisation>, SlamError>>,
    ),
}

struct CurrentKeyframe {
    id: usize,
    frame_index: usize,
    timestamp: f64,
    intensity: ImageF32,
    /// The reference frame's colour, kept with the keyframe (for coloured models and meshes).
    colour: Option<ColourImage>,
    frontworld_from_keyframe: Se3,
    link: KeyframeLink,
}

/// The RGB-ID SLAM system (see the module docs).
///
/// `Slam` is `Send`: it can move to another thread (bindings can release their interpreter
/// lock around [`Slam::process`]).
pub struct Slam {
    config: SlamConfig,
    camera: PinholeCamera,
    odometry: Odometry,
    fuser: KeyframeFuser,
    current: Option<CurrentKeyframe>,
    next_keyframe_id: usize,
    /// Frames since the last keyframe: inverse depth and front-end pose.
    /// Frames since the keyframe: inverse depth, `frontworld_from_camera`, the odometry's
    /// geometric scale sigma_W (1/m).
    buffer: std::collections::VecDeque<(ImageF32, Se3, f64)>,
    /// Buffered frames not yet fused into the current keyframe
    /// ([`BufferedFusion::OnePerFrame`]), oldest first, as in `buffer`.
    pending: std::collections::VecDeque<(ImageF32, Se3, f64)>,
    /// Covariance of the current keyframe relative to the chain's anchor (the newest odometry
    /// reference since the keyframe started), as a right perturbation in the anchor's frame
    /// (`[v; w]`, m and rad).
    chain_covariance: Covariance6,
    /// Front-end pose of the chain's anchor.
    frontworld_from_anchor: Se3,
    lost: bool,
    /// Time stamp (s) and front-end pose of the last frame with a pose, for the speed check.
    last_pose: Option<(f64, Se3)>,
    frames: Vec<FrameRecord>,
    tx: Option<SyncSender<ToBackend>>,
    handle: Option<JoinHandle<Result<Backend, SlamError>>>,
    shared: Arc<Mutex<Shared>>,
    session: u32,
    map_keyframes: usize,
    /// The event stream (off until [`Slam::events`] is called).
    events: Arc<EventHub>,
}

/// The covariance of a link whose odometry gave none (1 mm, 1 mrad).
fn default_cov() -> Covariance6 {
    Covariance6::from_diagonal([1e-6; 6])
}

impl Slam {
    /// Starts the system for frames of `camera` (undistorted pinhole) on `backend`. With a
    /// loaded `map`, the first frames relocalise in it and the map is extended.
    pub fn new(
        config: SlamConfig,
        camera: PinholeCamera,
        backend: &ComputeBackend,
        vocabulary: Vocabulary,
        map: Option<Map>,
    ) -> Result<Self, SlamError> {
        config.validate()?;
        let odometry = Odometry::new(config.odometry.clone(), camera, backend)?;
        let fuser = KeyframeFuser::new(camera, config.fusion, backend)?;
        let shared = Arc::new(Mutex::new(Shared::default()));
        let events = Arc::new(EventHub::default());
        let mut back = Backend::new(
            camera,
            config.clone(),
            backend,
            vocabulary,
            shared.clone(),
            events.clone(),
        )?;
        let mut session = 0;
        if let Some(map) = map {
            if map.camera != camera {
                return Err(SlamError::InvalidConfig(format!(
                    "the map was made with camera {:?}, this sequence has {:?}",
                    map.camera, camera
                )));
            }
            session = map.sessions;
            map.load_into(&mut back)?;
        }
        let map_keyframes = back.keyframes.len();
        back.note_memory();
        let (tx, rx) = sync_channel::<ToBackend>(config.queue);
        let handle = std::thread::Builder::new()
            .name("rgbid-backend".into())
            .spawn(move || backend_loop(back, rx))
            .map_err(|e| SlamError::BackendStopped(e.to_string()))?;
        Ok(Slam {
            config,
            camera,
            odometry,
            fuser,
            current: None,
            next_keyframe_id: map_keyframes,
            buffer: std::collections::VecDeque::new(),
            pending: std::collections::VecDeque::new(),
            chain_covariance: Covariance6::ZERO,
            frontworld_from_anchor: Se3::IDENTITY,
            lost: map_keyframes > 0,
            last_pose: None,
            frames: Vec::new(),
            tx: Some(tx),
            handle: Some(handle),
            shared,
            session,
            map_keyframes,
            events,
        })
    }

    /// Turns the event stream on (bounds: [`EventOptions::default`]) and returns its
    /// receiver; see [`crate::slam::events`]. Call it before the first
    /// [`process`](Self::process) to see every event; until it is called no event is made,
    /// so a run that does not want them pays nothing. Calling it again returns another
    /// receiver of the same queue.
    ///
    /// The system never waits for the receiver: when it lags, the oldest label images and,
    /// past the event bound, the oldest events are dropped ([`SlamEvents::dropped`]). The
    /// stream ends (the receiver reports "disconnected" once empty) when the system has
    /// finished or is dropped.
    pub fn events(&self) -> SlamEvents {
        self.events_with(EventOptions::default())
    }

    /// [`Self::events`] with other bounds.
    pub fn events_with(&self, options: EventOptions) -> SlamEvents {
        self.events.start(options);
        SlamEvents::new(self.events.clone())
    }

    /// Number of frames processed.
    pub fn frames(&self) -> usize {
        self.frames.len()
    }

    /// The memory this instance holds, by owner, and the peak of its total over the run
    /// (bytes; see [`MemoryBreakdown`] for what is counted). The front-end's parts are
    /// measured now, the back-end's as of its last keyframe: the back-end runs on its own
    /// thread. The peak is taken at every processed frame and every back-end keyframe. Cheap
    /// (sums of capacities, one lock); allocates nothing.
    pub fn memory(&self) -> MemoryReport {
        let shared = self
            .shared
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        let front = self.frontend_memory(loop_record_bytes(&shared.loop_records));
        shared.memory.report_with(&front)
    }

    /// The front-end's parts of the memory account; the loop records (kept in the state
    /// shared with the back-end) count `loop_records` bytes.
    fn frontend_memory(&self, loop_records: usize) -> MemoryBreakdown {
        let (odometry, odometry_gpu) = self.odometry.memory_bytes();
        let (fusion, fusion_gpu) = self.fuser.memory_bytes();
        let entry = std::mem::size_of::<(ImageF32, Se3, f64)>();
        let buffered = (self.buffer.capacity() + self.pending.capacity()) * entry
            + self
                .buffer
                .iter()
                .chain(&self.pending)
                .map(|(rho, _, _)| vec_bytes(&rho.data))
                .sum::<usize>();
        MemoryBreakdown {
            keyframes: self.current.as_ref().map_or(0, |c| {
                vec_bytes(&c.intensity.data) + c.colour.as_ref().map_or(0, |c| c.rgb().len())
            }),
            odometry,
            fusion: fusion + buffered,
            records: vec_bytes(&self.frames) + loop_records,
            gpu: odometry_gpu + fusion_gpu,
            ..MemoryBreakdown::default()
        }
    }

    /// Enters the front-end's parts in the memory account.
    fn note_memory(&self) {
        let mut shared = self
            .shared
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        let front = self.frontend_memory(loop_record_bytes(&shared.loop_records));
        shared.memory.set_frontend(front);
    }

    fn send(&mut self, msg: ToBackend) -> Result<(), SlamError> {
        let Some(tx) = &self.tx else {
            return Err(SlamError::BackendStopped("already finished".into()));
        };
        if tx.send(msg).is_err() {
            return Err(self.backend_failure());
        }
        Ok(())
    }

    /// The error the back-end thread stopped with.
    fn backend_failure(&mut self) -> SlamError {
        self.tx = None;
        match self.handle.take().map(|h| h.join()) {
            Some(Ok(Err(e))) => e,
            Some(Err(_)) => SlamError::BackendStopped("the back-end thread panicked".into()),
            _ => SlamError::BackendStopped("the back-end stopped".into()),
        }
    }

    fn finish_keyframe(&mut self) -> Result<(), SlamError> {
        // Frames still waiting are fused now, so the keyframe takes in the same frames
        // whatever the schedule.
        while self.fuse_one_pending()? {}
        let Some(cur) = self.current.take() else {
            return Ok(());
        };
        let (rho, weight) = self.fuser.finish()?;
        let kf = Keyframe::pack(
            cur.id,
            cur.frame_index,
            self.session,
            cur.timestamp,
            &cur.intensity,
            &rho,
            &weight,
            cur.frontworld_from_keyframe,
            cur.link,
        );
        let kf = match cur.colour {
            // The frame's constructors checked the colour's size against the frame's.
            Some(c) => kf
                .with_colour(c)
                .map_err(|e| SlamError::Internal(e.to_string()))?,
            None => kf,
        };
        self.send(ToBackend::Keyframe(Box::new(kf)))
    }

    /// Starts a keyframe from `frame` and fuses the buffered frames into it.
    fn start_keyframe(
        &mut self,
        index: usize,
        frame: &RgbdFrame,
        frontworld_from_camera: Se3,
        link: KeyframeLink,
    ) -> Result<usize, SlamError> {
        let id = self.next_keyframe_id;
        self.next_keyframe_id += 1;
        self.fuser.start(&frame.inverse_depth)?;
        let buffered = std::mem::take(&mut self.buffer);
        match self.config.buffered_fusion {
            BufferedFusion::AtStart => {
                for (rho, frontworld_from_b, sigma_geo) in &buffered {
                    let b_from_kf = frontworld_from_b.inverse() * frontworld_from_camera;
                    self.fuser.fuse(rho, &b_from_kf, *sigma_geo)?;
                }
            }
            BufferedFusion::OnePerFrame => self.pending = buffered,
        }
        self.current = Some(CurrentKeyframe {
            id,
            frame_index: index,
            timestamp: frame.timestamp,
            intensity: frame.intensity.clone(),
            colour: if self.config.keyframe_colour {
                frame.colour().cloned()
            } else {
                None
            },
            frontworld_from_keyframe: frontworld_from_camera,
            link,
        });
        if self.events.on() {
            self.events.push(SlamEvent::KeyframeCreated {
                id,
                frame_index: index,
                timestamp: frame.timestamp,
                world_from_keyframe: self.correction() * frontworld_from_camera,
                link,
            });
        }
        self.chain_covariance = Covariance6::ZERO;
        self.frontworld_from_anchor = frontworld_from_camera;
        Ok(id)
    }

    /// Fuses the newest buffered frame still waiting into the current keyframe; false when
    /// none waits (or no keyframe is open).
    fn fuse_one_pending(&mut self) -> Result<bool, SlamError> {
        let Some(frontworld_from_kf) = self.current.as_ref().map(|c| c.frontworld_from_keyframe)
        else {
            self.pending.clear();
            return Ok(false);
        };
        let Some((rho, frontworld_from_b, sigma_geo)) = self.pending.pop_back() else {
            return Ok(false);
        };
        let b_from_kf = frontworld_from_b.inverse() * frontworld_from_kf;
        self.fuser.fuse(&rho, &b_from_kf, sigma_geo)?;
        Ok(true)
    }

    fn check_frame(&self, index: usize, frame: &RgbdFrame) -> Result<(), SlamError> {
        let (w, h) = (self.camera.width as usize, self.camera.height as usize);
        if frame.width() != w
            || frame.height() != h
            || frame.intensity.data.len() != w * h
            || frame.inverse_depth.data.len() != w * h
        {
            return Err(SlamError::FrameSize {
                index,
                got_w: frame.width(),
                got_h: frame.height(),
                want_w: w,
                want_h: h,
            });
        }
        Ok(())
    }

    fn correction(&self) -> Se3 {
        self.shared
            .lock()
            .map(|s| s.correction)
            .unwrap_or(Se3::IDENTITY)
    }

    fn counts(&self) -> (usize, usize) {
        self.shared
            .lock()
            .map(|s| (s.keyframes, s.loops))
            .unwrap_or((0, 0))
    }

    fn report(&mut self, record: FrameRecord) -> FrameReport {
        self.frames.push(record);
        self.note_memory();
        let (keyframes, loops) = self.counts();
        FrameReport {
            record,
            status: record.status,
            world_from_camera: record.frontworld_from_camera.map(|p| self.correction() * p),
            keyframes,
            loops,
        }
    }

    /// Loop records the back-end has made so far (accepted and rejected, relocalisation
    /// included), from the `first`-th on, in the order they were found (the order of
    /// [`SlamResult::loops`]). The back-end runs on its own thread: a keyframe's loop shows
    /// up some frames after the keyframe was finished, and those still pending at the end
    /// are only in [`SlamResult::loops`]. A relocalisation attempt is answered within
    /// [`Slam::process`], so its record is there when `process` returns.
    pub fn loops_since(&self, first: usize) -> Vec<LoopRecord> {
        self.shared
            .lock()
            .map(|s| s.loop_records.get(first..).unwrap_or_default().to_vec())
            .unwrap_or_default()
    }

    /// Whether the motion from the last posed frame to `world_from_camera` is within the
    /// configured speed bounds (true when there is no previous pose or no time difference).
    fn plausible_motion(&self, index: usize, timestamp: f64, world_from_camera: &Se3) -> bool {
        let Some((t0, p0)) = self.last_pose else {
            return true;
        };
        let dt = timestamp - t0;
        if !(dt > 0.0 && dt.is_finite()) {
            return true;
        }
        let rel = p0.inverse() * *world_from_camera;
        let speed = rel.translation.length() / dt;
        let angular = crate::geometry::so3_log(rel.rotation).length() / dt;
        let ok =
            speed <= self.config.lost_max_speed && angular <= self.config.lost_max_angular_speed;
        if !ok {
            log::warn!(
                "frame {index}: implausible motion ({speed:.2} m/s, {angular:.2} rad/s; bounds \
                 {} m/s, {} rad/s): treated as a tracking failure",
                self.config.lost_max_speed,
                self.config.lost_max_angular_speed
            );
        }
        ok
    }

    /// Tries to relocalise `frame`; on success the odometry restarts there.
    fn try_relocalise(
        &mut self,
        index: usize,
        frame: &RgbdFrame,
    ) -> Result<Option<Se3>, SlamError> {
        let (rtx, rrx) = channel();
        self.send(ToBackend::Relocalise(Box::new(frame.clone()), rtx))?;
        let answer = match rrx.recv() {
            Ok(a) => a?,
            Err(_) => return Err(self.backend_failure()),
        };
        let Some(r) = answer else {
            return Ok(None);
        };
        let frontworld_from_camera = r.frontworld_from_keyframe * r.keyframe_from_frame;
        if self.events.on() {
            self.events.push(SlamEvent::Relocalised {
                frame_index: index,
                timestamp: frame.timestamp,
                keyframe: r.keyframe,
                new_keyframe: self.next_keyframe_id,
                world_from_camera: self.correction() * frontworld_from_camera,
            });
        }
        self.odometry.reset(frontworld_from_camera);
        // The first tracked frame builds the odometry reference.
        self.odometry.track(frame)?;
        self.buffer.clear();
        self.pending.clear();
        let link = KeyframeLink::Relocalised {
            from: r.keyframe,
            from_from_this: r.keyframe_from_frame,
            covariance: r.covariance.unwrap_or_else(default_cov),
        };
        self.start_keyframe(index, frame, frontworld_from_camera, link)?;
        Ok(Some(frontworld_from_camera))
    }

    /// Processes the next frame (front-end; keyframes go to the back-end thread).
    pub fn process(&mut self, frame: &RgbdFrame) -> Result<FrameReport, SlamError> {
        let index = self.frames.len();
        self.check_frame(index, frame)?;
        let t0 = Instant::now();
        let mut record = FrameRecord {
            index,
            timestamp: frame.timestamp,
            status: FrameStatus::Lost,
            frontworld_from_camera: None,
            keyframe: None,
            frontend_ms: 0.0,
            times: StageTimes::default(),
            fusion_ms: 0.0,
            covisibility: 0.0,
            keyframe_covisibility: 0.0,
            diagnostics: OdometryDiagnostics::default(),
            odometry_covariance: None,
            keyframe_covariance: None,
        };
        // Start of the first session: this frame is the origin.
        if self.current.is_none() && !self.lost {
            self.odometry.reset(Se3::IDENTITY);
            let r = self.odometry.track(frame)?;
            let id = self.start_keyframe(index, frame, r.world_from_camera, KeyframeLink::First)?;
            self.last_pose = Some((frame.timestamp, r.world_from_camera));
            record.status = FrameStatus::NewKeyframe;
            record.frontworld_from_camera = Some(r.world_from_camera);
            record.keyframe = Some((id, Se3::IDENTITY));
            record.covisibility = 1.0;
            record.keyframe_covisibility = 1.0;
            record.frontend_ms = t0.elapsed().as_secs_f64() * 1e3;
            return Ok(self.report(record));
        }
        if self.lost {
            let every = self.config.relocalise_every.max(1);
            if index.is_multiple_of(every) {
                if let Some(p) = self.try_relocalise(index, frame)? {
                    self.lost = false;
                    self.last_pose = Some((frame.timestamp, p));
                    record.status = FrameStatus::Relocalised;
                    record.frontworld_from_camera = Some(p);
                    record.keyframe = self.current.as_ref().map(|c| (c.id, Se3::IDENTITY));
                    record.covisibility = 1.0;
                    record.keyframe_covisibility = 1.0;
                }
            }
            record.frontend_ms = t0.elapsed().as_secs_f64() * 1e3;
            return Ok(self.report(record));
        }
        // With a rolling shutter the rectified frame is the one tracked, fused and kept.
        let rectified = self.odometry.rectified(frame);
        let frame = rectified.as_ref().unwrap_or(frame);
        // Tracking.
        let tracked = match self.odometry.track_as_given(frame) {
            Ok(r) => Some(r),
            Err(crate::odometry::OdometryError::Gpu(e)) => return Err(SlamError::Gpu(e)),
            Err(e) => {
                log::warn!("frame {index}: tracking failed ({e}); relocalising");
                None
            }
        };
        let ok = tracked.as_ref().is_some_and(|r| {
            r.stats.covisibility >= self.config.lost_covisibility
                && r.stats.condition_number <= self.config.lost_condition
                && r.world_from_camera.is_finite()
                && self.plausible_motion(index, frame.timestamp, &r.world_from_camera)
        });
        let Some(r) = tracked.filter(|_| ok) else {
            // Lost: the current keyframe is finished and the frame gets no pose.
            if self.events.on() {
                self.events.push(SlamEvent::Lost {
                    frame_index: index,
                    timestamp: frame.timestamp,
                });
            }
            self.finish_keyframe()?;
            self.buffer.clear();
            self.pending.clear();
            self.lost = true;
            self.last_pose = None;
            record.frontend_ms = t0.elapsed().as_secs_f64() * 1e3;
            return Ok(self.report(record));
        };
        record.times = r.stats.times;
        record.covisibility = r.stats.covisibility;
        record.diagnostics = OdometryDiagnostics {
            sigma_photo: r.stats.sigma_photo,
            sigma_geo: r.stats.sigma_geo,
            nu: r.stats.nu,
            condition_number: r.stats.condition_number,
            iterations: r.stats.iterations,
            new_reference: r.stats.new_reference,
        };
        record.status = FrameStatus::Tracking;
        let frontworld_from_camera = r.world_from_camera;
        // The odometry covariance is of ref_from_cur (right perturbation, current frame):
        // the chain is carried to that frame by the adjoint before it is added (a
        // first-order composition).
        let anchor_from_camera = self.frontworld_from_anchor.inverse() * frontworld_from_camera;
        if r.stats.new_reference {
            self.chain_covariance = self.chain_covariance.transported(&anchor_from_camera);
            if let Some(c) = r.covariance {
                self.chain_covariance = self.chain_covariance + c;
            }
            self.frontworld_from_anchor = frontworld_from_camera;
        }
        record.frontworld_from_camera = Some(frontworld_from_camera);
        self.last_pose = Some((frame.timestamp, frontworld_from_camera));
        let cur = self
            .current
            .as_ref()
            .ok_or_else(|| SlamError::Internal("tracking without keyframe".into()))?;
        let (kf_id, frontworld_from_kf) = (cur.id, cur.frontworld_from_keyframe);
        let kf_from_camera = frontworld_from_kf.inverse() * frontworld_from_camera;
        // The fusion tolerance in sigma_W needs the scale in 1/m: with the depth
        // parametrisation it is in m, and 0 makes the fuser use its fixed tolerance.
        let sigma_geo = match self.config.odometry.geometric {
            GeometricParam::InverseDepth => r.stats.sigma_geo,
            GeometricParam::Depth => 0.0,
        };
        let tf = Instant::now();
        // On a worker of the pool, as the tracking (`in_pool`). Nothing in here waits for
        // the back-end, whose own parallel passes need a free worker.
        let counts = crate::odometry::in_pool(|| {
            let counts =
                self.fuser
                    .fuse(&frame.inverse_depth, &kf_from_camera.inverse(), sigma_geo)?;
            self.fuse_one_pending()?;
            Ok::<_, SlamError>(counts)
        })?;
        record.fusion_ms = tf.elapsed().as_secs_f64() * 1e3;
        record.keyframe_covisibility = counts.covisibility();
        record.keyframe = Some((kf_id, kf_from_camera));
        let mut covariance = if r.stats.new_reference {
            self.chain_covariance
        } else {
            self.chain_covariance.transported(&anchor_from_camera)
        };
        if !r.stats.new_reference {
            if let Some(c) = r.covariance {
                covariance = covariance + c;
            }
        }
        record.odometry_covariance = r.covariance;
        record.keyframe_covariance = (!covariance.is_zero()).then_some(covariance);
        if counts.covisibility() < self.config.keyframe_covisibility {
            if covariance.is_zero() {
                covariance = default_cov();
            }
            self.finish_keyframe()?;
            let tf = Instant::now();
            let link = KeyframeLink::Odometry {
                from: kf_id,
                from_from_this: kf_from_camera,
                covariance,
            };
            let id = self.start_keyframe(index, frame, frontworld_from_camera, link)?;
            record.fusion_ms += tf.elapsed().as_secs_f64() * 1e3;
            record.status = FrameStatus::NewKeyframe;
            record.keyframe = Some((id, Se3::IDENTITY));
        } else {
            self.buffer.push_back((
                frame.inverse_depth.clone(),
                frontworld_from_camera,
                sigma_geo,
            ));
            if self.buffer.len() > self.config.buffer_frames {
                self.buffer.pop_front();
            }
        }
        record.frontend_ms = t0.elapsed().as_secs_f64() * 1e3;
        Ok(self.report(record))
    }

    /// Finishes the run: sends the last keyframe, waits for the back-end, optimises the
    /// keyframe graph once more (if loops are pending) and then every frame with the keyframes
    /// fixed, and returns the results.
    pub fn finish(mut self) -> Result<SlamResult, SlamError> {
        self.finish_keyframe()?;
        self.tx = None;
        let mut back = match self.handle.take().map(|h| h.join()) {
            Some(Ok(Ok(b))) => b,
            Some(Ok(Err(e))) => return Err(e),
            Some(Err(_)) => {
                return Err(SlamError::BackendStopped(
                    "the back-end thread panicked".into(),
                ))
            }
            None => return Err(SlamError::BackendStopped("no back-end".into())),
        };
        let t = Instant::now();
        back.optimise()?;
        let keyframe_poses = back.keyframe_poses();
        let trajectory = optimise_frames(&self.frames, &keyframe_poses, self.config.frame_edges)?;
        let final_optimise_ms = t.elapsed().as_secs_f64() * 1e3;
        let odometry = self
            .frames
            .iter()
            .filter_map(|f| {
                f.frontworld_from_camera.map(|p| TimedPose {
                    timestamp: f.timestamp,
                    world_from_camera: p,
                })
            })
            .collect();
        let memory = self.memory();
        let map = Map::from_backend(&mut back, self.session + 1);
        let timings = back.timings.clone();
        Ok(SlamResult {
            frames: std::mem::take(&mut self.frames),
            trajectory,
            odometry,
            keyframe_poses,
            loops: std::mem::take(
                &mut self
                    .shared
                    .lock()
                    .unwrap_or_else(std::sync::PoisonError::into_inner)
                    .loop_records,
            ),
            timings,
            map,
            final_optimise_ms,
            memory,
        })
    }

    /// Keyframes of a loaded map.
    pub fn map_keyframes(&self) -> usize {
        self.map_keyframes
    }
}

impl SlamResult {
    /// All keyframes (those of a loaded map included); their `world_from_keyframe` is the
    /// optimised pose (they live in [`Self::map`]).
    pub fn keyframes(&self) -> &[Keyframe] {
        &self.map.keyframes
    }

    /// The keyframes' optimised `world_from_keyframe` with their time stamps, in keyframe
    /// order (what `keyframes.txt` of a run folder holds).
    pub fn keyframe_trajectory(&self) -> Vec<TimedPose> {
        self.keyframes()
            .iter()
            .zip(&self.keyframe_poses)
            .map(|(k, p)| TimedPose {
                timestamp: k.timestamp,
                world_from_camera: *p,
            })
            .collect()
    }

    /// The keyframes' surface as a mesh: the zero level set of [`SlamResult::volume`].
    pub fn mesh(
        &self,
        camera: &PinholeCamera,
        voxel: f64,
        backend: &ComputeBackend,
    ) -> Result<crate::tsdf::Mesh, crate::tsdf::TsdfError> {
        self.volume(camera, voxel, backend)?.extract_mesh()
    }

    /// The keyframes' TSDF volume (world frame): their fused inverse depth (and colour)
    /// integrated into a TSDF of `voxel` metres at their optimised poses, with the default
    /// truncation and the model's minimum fusion weight ([`super::build_volume`] with those
    /// settings); `camera` is the keyframes' (undistorted pinhole, pixels).
    pub fn volume(
        &self,
        camera: &PinholeCamera,
        voxel: f64,
        backend: &ComputeBackend,
    ) -> Result<crate::tsdf::TsdfVolume, crate::tsdf::TsdfError> {
        let params = crate::tsdf::TsdfParams {
            voxel_size: voxel,
            ..Default::default()
        };
        super::build_volume(
            self.keyframes(),
            &self.keyframe_poses,
            camera,
            &params,
            super::ModelParams::default().min_weight,
            backend,
        )
    }
}

impl Drop for Slam {
    fn drop(&mut self) {
        self.tx = None;
        if let Some(h) = self.handle.take() {
            let _ = h.join();
        }
        self.events.close();
    }
}

fn backend_loop(back: Backend, rx: Receiver<ToBackend>) -> Result<Backend, SlamError> {
    let mut back = backend_messages(back, rx)?;
    // No more keyframes to segment: free the segmentation's buffers (~130-160 bytes per pixel).
    back.segmenter.release();
    back.note_memory();
    Ok(back)
}

/// The back-end's message loop, until the front-end hangs up or an error stops it.
fn backend_messages(mut back: Backend, rx: Receiver<ToBackend>) -> Result<Backend, SlamError> {
    while let Ok(msg) = rx.recv() {
        match msg {
            ToBackend::Keyframe(kf) => {
                back.process(*kf)?;
                back.note_memory();
            }
            ToBackend::Relocalise(frame, reply) => {
                let answer = back.relocalise(&frame);
                back.note_memory();
                let failure = answer.as_ref().err().map(|e| e.to_string());
                let _ = reply.send(answer);
                if let Some(why) = failure {
                    return Err(SlamError::BackendStopped(format!(
                        "relocalisation failed: {why}"
                    )));
                }
            }
        }
    }
    Ok(back)
}

/// All frames with the keyframes fixed: one vertex per tracked frame, an edge to its
/// keyframe (`keyframe_from_camera`) and one to the previous tracked frame of the same
/// tracking run, weighted as `edges` says (thesis eq. 6.28).
fn optimise_frames(
    frames: &[FrameRecord],
    keyframe_poses: &[Se3],
    edges: FrameEdges,
) -> Result<Vec<TimedPose>, SlamError> {
    let mut g = PoseGraph3::new();
    let kf_offset = frames.len() as i64;
    for (k, p) in keyframe_poses.iter().enumerate() {
        let idx = g.add_vertex(kf_offset + k as i64, *p)?;
        g.fixed[idx] = true;
    }
    let mut prev: Option<(usize, Se3, &FrameRecord)> = None;
    let mut since_kf = 0usize;
    for f in frames {
        let (Some(p), Some((kf, kf_from_cam))) = (f.frontworld_from_camera, f.keyframe) else {
            prev = None;
            continue;
        };
        let Some(world_from_kf) = keyframe_poses.get(kf) else {
            return Err(SlamError::Internal(format!(
                "frame {} refers to keyframe {kf} of {}",
                f.index,
                keyframe_poses.len()
            )));
        };
        g.add_vertex(f.index as i64, *world_from_kf * kf_from_cam)?;
        since_kf = if f.status == FrameStatus::NewKeyframe || f.status == FrameStatus::Relocalised {
            0
        } else {
            since_kf + 1
        };
        let s = 0.002 * (1.0 + since_kf as f64).sqrt();
        let kf_covariance = match edges {
            FrameEdges::Fixed => None,
            FrameEdges::Odometry => f.keyframe_covariance,
        };
        g.add_edge(
            kf_offset + kf as i64,
            f.index as i64,
            kf_from_cam,
            information_from(kf_covariance.as_ref(), s, s),
        )?;
        if let Some((pi, p_prev, r_prev)) = prev {
            if f.status != FrameStatus::Relocalised {
                let prev_from_cur = p_prev.inverse() * p;
                let covariance = match edges {
                    FrameEdges::Fixed => None,
                    // The previous frame became the reference: the alignment is the edge.
                    FrameEdges::Odometry if r_prev.diagnostics.new_reference => {
                        f.odometry_covariance
                    }
                    // Both aligned to the same reference: the previous frame's covariance
                    // carried into this frame, plus this frame's.
                    FrameEdges::Odometry => {
                        match (r_prev.odometry_covariance, f.odometry_covariance) {
                            (Some(a), Some(b)) => Some(a.transported(&prev_from_cur) + b),
                            _ => None,
                        }
                    }
                };
                g.add_edge(
                    pi as i64,
                    f.index as i64,
                    prev_from_cur,
                    information_from(covariance.as_ref(), 0.002, 0.002),
                )?;
            }
        }
        prev = Some((f.index, p, f));
    }
    if g.edges.is_empty() {
        // Nothing to optimise (a single frame).
    } else {
        g.optimize(&SolverOptions {
            max_iterations: 20,
            ..Default::default()
        })?;
    }
    Ok(frames
        .iter()
        .filter_map(|f| {
            g.index_of(f.index as i64).map(|i| TimedPose {
                timestamp: f.timestamp,
                world_from_camera: g.poses[i],
            })
        })
        .collect())
}

// `Slam` moves to other threads (bindings release their interpreter lock around `process`).
const _: fn() = || {
    fn send<T: Send>() {}
    send::<Slam>();
};

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn gaussian(rng: &mut impl Rng) -> f64 {
        let u: f64 = rng.random::<f64>().max(1e-300);
        let v: f64 = rng.random();
        (-2.0 * u.ln()).sqrt() * (2.0 * std::f64::consts::PI * v).cos()
    }

    /// First-order composition of two noisy relative poses against Monte Carlo:
    /// `a_from_c = a_from_b exp(d1) b_from_c exp(d2)` has the right-perturbation covariance
    /// `Ad(c_from_b) C1 Ad(c_from_b)^T + C2` in frame `c`.
    #[test]
    fn chain_covariance_follows_the_adjoint() {
        let a_from_b = Se3::exp(&[0.3, -0.1, 0.5, 0.2, -0.4, 0.3]);
        let b_from_c = Se3::exp(&[0.8, 0.2, -0.3, -0.3, 0.5, 0.1]);
        let sd1 = [0.01, 0.02, 0.005, 0.004, 0.01, 0.002];
        let sd2 = [0.003, 0.001, 0.002, 0.001, 0.002, 0.003];
        let diag = |s: &[f64; 6]| Covariance6::from_diagonal(s.map(|v| v * v));
        let predicted = diag(&sd1).transported(&b_from_c) + diag(&sd2);
        let mut rng = rand_pcg::Pcg64::seed_from_u64(7);
        let n = 40_000;
        let mut acc = [[0.0; 6]; 6];
        let mean = a_from_b * b_from_c;
        for _ in 0..n {
            let mut d1 = [0.0; 6];
            let mut d2 = [0.0; 6];
            for i in 0..6 {
                let g1 = gaussian(&mut rng);
                let g2 = gaussian(&mut rng);
                d1[i] = g1 * sd1[i];
                d2[i] = g2 * sd2[i];
            }
            let x = a_from_b * Se3::exp(&d1) * b_from_c * Se3::exp(&d2);
            let e = (mean.inverse() * x).log();
            for i in 0..6 {
                for j in 0..6 {
                    acc[i][j] += e[i] * e[j] / n as f64;
                }
            }
        }
        // Without the adjoint (the old sum C1 + C2) the prediction is far off.
        let naive = diag(&sd1) + diag(&sd2);
        let err = |c: &Covariance6| -> f64 {
            let c = c.rows();
            let mut num = 0.0;
            let mut den = 0.0;
            for i in 0..6 {
                for j in 0..6 {
                    num += (c[i][j] - acc[i][j]).powi(2);
                    den += acc[i][j].powi(2);
                }
            }
            (num / den).sqrt()
        };
        assert!(err(&predicted) < 0.05, "adjoint {}", err(&predicted));
        assert!(err(&naive) > 0.3, "naive {}", err(&naive));
    }

    /// Two frames under one keyframe whose keyframe edge and frame-to-frame edge disagree
    /// (10 cm against 20 cm): with the odometry covariances the confident keyframe edge wins,
    /// with the fixed sigmas the frame lands between the two.
    #[test]
    fn frame_edges_follow_the_odometry_covariances() {
        use glam::DVec3;
        let at = |x: f64| Se3::new(glam::DQuat::IDENTITY, DVec3::new(x, 0.0, 0.0));
        let record = |index: usize, status, front: Se3, kf_from_cam: Se3| FrameRecord {
            index,
            timestamp: index as f64 / 30.0,
            status,
            frontworld_from_camera: Some(front),
            keyframe: Some((0, kf_from_cam)),
            frontend_ms: 0.0,
            times: StageTimes::default(),
            fusion_ms: 0.0,
            covisibility: 1.0,
            keyframe_covisibility: 1.0,
            diagnostics: OdometryDiagnostics::default(),
            odometry_covariance: None,
            keyframe_covariance: None,
        };
        let mut first = record(0, FrameStatus::NewKeyframe, Se3::IDENTITY, Se3::IDENTITY);
        // The first frame is the second one's odometry reference.
        first.diagnostics.new_reference = true;
        let mut second = record(1, FrameStatus::Tracking, at(0.2), at(0.1));
        second.odometry_covariance = Some(Covariance6::from_diagonal([1.0; 6]));
        second.keyframe_covariance = Some(Covariance6::from_diagonal([1e-6; 6]));
        let frames = [first, second];
        let x = |edges| -> f64 {
            let t = optimise_frames(&frames, &[Se3::IDENTITY], edges).expect("frame graph");
            t[1].world_from_camera.translation.x
        };
        let odometry = x(FrameEdges::Odometry);
        let fixed = x(FrameEdges::Fixed);
        assert!((odometry - 0.1).abs() < 2e-3, "odometry edges: {odometry}");
        assert!(fixed > 0.12 && fixed < 0.19, "fixed edges: {fixed}");
    }
}
