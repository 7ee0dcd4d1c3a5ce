//! What the SLAM system did, as it happens: a bounded, non-blocking event stream.
//!
//! [`Slam::events`](super::Slam::events) turns the stream on and returns its receiver,
//! [`SlamEvents`]. Until then nothing is built or queued. Both threads of the system (the
//! front-end on the caller's thread, the back-end on its own) push into one queue in the
//! order things happen; pushing never waits for the consumer. When the consumer lags, the
//! queue keeps its bounds ([`EventOptions`]) by dropping, oldest first, the label images of
//! described keyframes (the event stays, in its light form) and, past the event bound, whole
//! events; both are counted ([`SlamEvents::dropped`]).
//!
//! Poses are `world_from_*` (`p_world = world_from_camera * p_camera`; metres, radians), in
//! the map's world frame as corrected by the loop closures known when the event was made.
//! Keyframe ids are the ids of [`Keyframe::id`](super::Keyframe::id) and
//! [`LoopRecord`]; frame indices count the frames given to [`Slam::process`](super::Slam::process)
//! from 0.
//!
//! ```no_run
//! # use rgbid::slam::{Slam, SlamError, SlamEvent};
//! # fn f(mut slam: Slam, frames: Vec<rgbid::image::RgbdFrame>) -> Result<(), SlamError> {
//! let events = slam.events();
//! for frame in &frames {
//!     slam.process(frame)?;
//!     for event in events.try_iter() {
//!         if let SlamEvent::LoopChecked(l) = event {
//!             println!("loop {} -> {}: {}", l.query, l.candidate, l.verdict);
//!         }
//!     }
//! }
//! let result = slam.finish()?;
//! // The rest (the back-end's last keyframes, the final optimisation), to the end.
//! for event in events.iter() {
//!     println!("{event:?}");
//! }
//! println!("{} keyframes; dropped {:?}", result.keyframes().len(), events.dropped());
//! # Ok(()) }
//! ```

use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{RecvError, RecvTimeoutError, TryRecvError};
use std::sync::{Arc, Condvar, Mutex, MutexGuard, PoisonError};
use std::time::{Duration, Instant};

use super::backend::LoopRecord;
use super::keyframe::KeyframeLink;
use crate::geometry::Se3;
use crate::image::ImageF32;
use crate::place::KeyPoint;

/// One thing the SLAM system did. Events are `Send`; they are made only while the stream is
/// on (see the [module docs](self)).
// A few events per keyframe: their size (a keyframe link holds a 6x6 covariance) does not
// matter, and unboxed variants are simpler to match.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Debug)]
#[non_exhaustive]
pub enum SlamEvent {
    /// The front-end started a keyframe from a frame (the keyframe is finished, with the
    /// frames fused into it, when the next one starts; the back-end describes it then).
    KeyframeCreated {
        /// Keyframe id.
        id: usize,
        /// Index of the frame it was made from.
        frame_index: usize,
        /// Time stamp of that frame, seconds.
        timestamp: f64,
        /// `world_from_keyframe` (the camera of that frame), corrected by the loops known then.
        world_from_keyframe: Se3,
        /// How it is attached to the map (`from_from_this` is relative, so not corrected).
        link: KeyframeLink,
    },
    /// The back-end described a keyframe for place recognition: superjuts, neg-entropy
    /// masks, ORB keypoints.
    KeyframeDescribed(KeyframeDescribed),
    /// The back-end checked a loop (or a relocalisation) candidate that passed the
    /// geometric verification: the record, with its verdict, exactly as it is in
    /// [`SlamResult::loops`](super::SlamResult::loops).
    LoopChecked(LoopRecord),
    /// The keyframe pose graph was optimised (a loop cluster closed, or the final
    /// optimisation in [`Slam::finish`](super::Slam::finish)).
    GraphOptimised {
        /// Optimised `world_from_keyframe` of every keyframe, indexed by keyframe id.
        world_from_keyframe: Vec<Se3>,
        /// Accepted loops (relocalisations included) so far.
        loops: usize,
        /// Time of the optimisation, milliseconds.
        optimise_ms: f64,
    },
    /// Tracking was lost on this frame (it gets no pose); relocalisation is tried on the next
    /// frames.
    Lost {
        /// Frame index.
        frame_index: usize,
        /// Time stamp, seconds.
        timestamp: f64,
    },
    /// The frame was relocalised against a keyframe; tracking goes on from it, in a new
    /// keyframe.
    Relocalised {
        /// Frame index.
        frame_index: usize,
        /// Time stamp, seconds.
        timestamp: f64,
        /// The keyframe it was relocalised against.
        keyframe: usize,
        /// The keyframe started at this frame.
        new_keyframe: usize,
        /// `world_from_camera` of the frame, corrected by the loops known then.
        world_from_camera: Se3,
    },
}

impl SlamEvent {
    /// Whether the event still holds a bulky payload (a label image) the queue may drop.
    pub fn has_images(&self) -> bool {
        matches!(self, SlamEvent::KeyframeDescribed(d) if d.labels.is_some())
    }

    /// Drops the bulky payload (the light form stays); true if there was one.
    fn drop_images(&mut self) -> bool {
        match self {
            SlamEvent::KeyframeDescribed(d) => d.labels.take().is_some(),
            _ => false,
        }
    }
}

/// How the back-end described a keyframe.
#[derive(Clone, Debug)]
pub struct KeyframeDescribed {
    /// Keyframe id.
    pub id: usize,
    /// Superjut label per pixel; `None` without masks (`SlamConfig::masks` off) or when the
    /// queue dropped it for a lagging consumer.
    pub labels: Option<SuperjutLabels>,
    /// Neg-entropy of each superjut (index = label; higher = more structure in its normals;
    /// the masks keep superjuts at or above their threshold). Empty without masks.
    pub neg_entropy: Vec<f64>,
    /// ORB keypoints of the keyframe (level-0 pixels).
    pub keypoints: Vec<KeyPoint>,
    /// Per mask, whether each keypoint lies inside it: the first mask is the whole image,
    /// then one per `SlamConfig::mask_thresholds` entry, in that order. Empty without masks.
    pub mask_flags: Vec<Vec<bool>>,
    /// Segmentation and masks time, milliseconds.
    pub segment_ms: f64,
    /// ORB extraction and bags of words time, milliseconds.
    pub describe_ms: f64,
}

impl KeyframeDescribed {
    /// Per-pixel neg-entropy of the pixel's superjut (`NaN` where there is none); `None`
    /// without the label image.
    pub fn neg_entropy_image(&self) -> Option<ImageF32> {
        let l = self.labels.as_ref()?;
        let data = l
            .labels
            .iter()
            .map(|&s| {
                self.neg_entropy
                    .get(s as usize)
                    .map_or(f32::NAN, |&v| v as f32)
            })
            .collect();
        ImageF32::from_vec(l.width, l.height, data)
    }
}

/// A superjut label image (the bulky part of [`KeyframeDescribed`]).
#[derive(Clone, Debug, PartialEq)]
pub struct SuperjutLabels {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// Row-major superjut label per pixel;
    /// [`NO_SEGMENT`](crate::segment::NO_SEGMENT) where there is no depth or normal.
    pub labels: Vec<u32>,
}

/// Bounds of the event queue.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct EventOptions {
    /// Most events queued; past it the oldest event is dropped (counted in
    /// [`EventDrops::events`]). At least 1.
    pub capacity: usize,
    /// Most label images queued (each `4 * width * height` bytes); past it the oldest one is
    /// dropped and its event stays in its light form (counted in [`EventDrops::images`]).
    /// 0 queues none.
    pub images: usize,
}

impl Default for EventOptions {
    fn default() -> Self {
        EventOptions {
            capacity: 1024,
            images: 8,
        }
    }
}

/// What the queue dropped because the consumer lagged.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct EventDrops {
    /// Label images dropped (their events were kept in light form).
    pub images: u64,
    /// Whole events dropped.
    pub events: u64,
}

impl EventDrops {
    /// Images and events dropped.
    pub fn total(&self) -> u64 {
        self.images + self.events
    }
}

#[derive(Debug, Default)]
struct Queue {
    events: VecDeque<SlamEvent>,
    /// Events in `events` that hold images.
    with_images: usize,
    options: EventOptions,
    dropped: EventDrops,
    /// The system finished or was dropped: no more events will come.
    closed: bool,
}

/// The queue shared by the system's threads and the receivers.
#[derive(Debug, Default)]
pub(crate) struct EventHub {
    on: AtomicBool,
    queue: Mutex<Queue>,
    ready: Condvar,
}

impl EventHub {
    /// Whether events are wanted (one atomic load: the cost of the stream when it is off).
    pub fn on(&self) -> bool {
        self.on.load(Ordering::Relaxed)
    }

    fn lock(&self) -> MutexGuard<'_, Queue> {
        self.queue.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Turns the stream on with `options`.
    pub fn start(&self, options: EventOptions) {
        let mut q = self.lock();
        q.options = EventOptions {
            capacity: options.capacity.max(1),
            images: options.images,
        };
        self.on.store(true, Ordering::Relaxed);
    }

    /// Queues `event` if the stream is on (never waits for a consumer).
    pub fn push(&self, mut event: SlamEvent) {
        if !self.on() {
            return;
        }
        let mut q = self.lock();
        if q.closed {
            return;
        }
        if event.has_images() {
            if q.options.images == 0 {
                event.drop_images();
                q.dropped.images += 1;
            } else {
                while q.with_images >= q.options.images {
                    let Some(old) = q.events.iter_mut().find(|e| e.has_images()) else {
                        break;
                    };
                    old.drop_images();
                    q.with_images -= 1;
                    q.dropped.images += 1;
                }
            }
        }
        while q.events.len() >= q.options.capacity {
            let Some(old) = q.events.pop_front() else {
                break;
            };
            if old.has_images() {
                q.with_images -= 1;
            }
            q.dropped.events += 1;
        }
        if event.has_images() {
            q.with_images += 1;
        }
        q.events.push_back(event);
        drop(q);
        self.ready.notify_all();
    }

    /// No more events will come (the system finished or was dropped).
    pub fn close(&self) {
        self.lock().closed = true;
        self.ready.notify_all();
    }

    fn pop(q: &mut Queue) -> Option<SlamEvent> {
        let e = q.events.pop_front()?;
        if e.has_images() {
            q.with_images -= 1;
        }
        Some(e)
    }
}

/// The receiving end of the event stream (see the [module docs](self)). Clones share one
/// queue: each event goes to one of them. The errors are those of `std::sync::mpsc`:
/// "disconnected" means the system finished (or was dropped) and every event was taken.
#[derive(Clone, Debug)]
pub struct SlamEvents {
    hub: Arc<EventHub>,
}

impl SlamEvents {
    pub(crate) fn new(hub: Arc<EventHub>) -> Self {
        SlamEvents { hub }
    }

    /// The oldest queued event, without waiting.
    pub fn try_recv(&self) -> Result<SlamEvent, TryRecvError> {
        let mut q = self.hub.lock();
        match EventHub::pop(&mut q) {
            Some(e) => Ok(e),
            None if q.closed => Err(TryRecvError::Disconnected),
            None => Err(TryRecvError::Empty),
        }
    }

    /// The oldest event, waiting for one at most `timeout`.
    pub fn recv_timeout(&self, timeout: Duration) -> Result<SlamEvent, RecvTimeoutError> {
        let deadline = Instant::now() + timeout;
        let mut q = self.hub.lock();
        loop {
            if let Some(e) = EventHub::pop(&mut q) {
                return Ok(e);
            }
            if q.closed {
                return Err(RecvTimeoutError::Disconnected);
            }
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Err(RecvTimeoutError::Timeout);
            }
            q = self
                .hub
                .ready
                .wait_timeout(q, left)
                .unwrap_or_else(PoisonError::into_inner)
                .0;
        }
    }

    /// The oldest event, waiting until there is one or the system has finished.
    pub fn recv(&self) -> Result<SlamEvent, RecvError> {
        let mut q = self.hub.lock();
        loop {
            if let Some(e) = EventHub::pop(&mut q) {
                return Ok(e);
            }
            if q.closed {
                return Err(RecvError);
            }
            q = self
                .hub
                .ready
                .wait(q)
                .unwrap_or_else(PoisonError::into_inner);
        }
    }

    /// Every event, oldest first, waiting for each: ends when the system has finished and
    /// the queue is empty.
    pub fn iter(&self) -> impl Iterator<Item = SlamEvent> + '_ {
        std::iter::from_fn(|| self.recv().ok())
    }

    /// The events queued now, oldest first, without waiting.
    pub fn try_iter(&self) -> impl Iterator<Item = SlamEvent> + '_ {
        std::iter::from_fn(|| self.try_recv().ok())
    }

    /// What the queue has dropped so far because the consumer lagged.
    pub fn dropped(&self) -> EventDrops {
        self.hub.lock().dropped
    }

    /// Events queued now.
    pub fn len(&self) -> usize {
        self.hub.lock().events.len()
    }

    /// Whether no event is queued now.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// Blocking iteration: every event until the system has finished and the queue is empty.
impl Iterator for SlamEvents {
    type Item = SlamEvent;

    fn next(&mut self) -> Option<SlamEvent> {
        self.recv().ok()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn described(id: usize) -> SlamEvent {
        SlamEvent::KeyframeDescribed(KeyframeDescribed {
            id,
            labels: Some(SuperjutLabels {
                width: 2,
                height: 1,
                labels: vec![0, 1],
            }),
            neg_entropy: vec![0.1, 0.9],
            keypoints: Vec::new(),
            mask_flags: Vec::new(),
            segment_ms: 0.0,
            describe_ms: 0.0,
        })
    }

    fn lost(i: usize) -> SlamEvent {
        SlamEvent::Lost {
            frame_index: i,
            timestamp: i as f64,
        }
    }

    #[test]
    fn off_queues_nothing() {
        let hub = Arc::new(EventHub::default());
        hub.push(lost(0));
        let rx = SlamEvents::new(hub.clone());
        assert!(matches!(rx.try_recv(), Err(TryRecvError::Empty)));
        hub.close();
        assert!(matches!(rx.try_recv(), Err(TryRecvError::Disconnected)));
    }

    #[test]
    fn oldest_images_then_oldest_events_are_dropped() {
        let hub = Arc::new(EventHub::default());
        hub.start(EventOptions {
            capacity: 4,
            images: 1,
        });
        for i in 0..3 {
            hub.push(described(i));
        }
        let rx = SlamEvents::new(hub.clone());
        assert_eq!(
            rx.dropped(),
            EventDrops {
                images: 2,
                events: 0
            }
        );
        hub.push(lost(3));
        hub.push(lost(4));
        assert_eq!(
            rx.dropped(),
            EventDrops {
                images: 2,
                events: 1
            }
        );
        let got: Vec<_> = rx.try_iter().collect();
        assert_eq!(got.len(), 4);
        // Event 0 went whole, event 1 lost its image, 2 kept it.
        match (&got[0], &got[1]) {
            (SlamEvent::KeyframeDescribed(a), SlamEvent::KeyframeDescribed(b)) => {
                assert_eq!((a.id, b.id), (1, 2));
                assert!(a.labels.is_none() && a.neg_entropy.len() == 2);
                let img = b.neg_entropy_image().unwrap();
                assert_eq!(img.data, vec![0.1, 0.9]);
            }
            other => panic!("{other:?}"),
        }
        // Images no longer counted once received: a new one is kept.
        hub.push(described(5));
        assert_eq!(rx.dropped().images, 2);
    }

    #[test]
    fn recv_ends_when_closed_and_waits_otherwise() {
        let hub = Arc::new(EventHub::default());
        hub.start(EventOptions::default());
        let rx = SlamEvents::new(hub.clone());
        assert!(matches!(
            rx.recv_timeout(Duration::from_millis(5)),
            Err(RecvTimeoutError::Timeout)
        ));
        let h = {
            let hub = hub.clone();
            std::thread::spawn(move || {
                hub.push(lost(0));
                hub.close();
            })
        };
        let all: Vec<_> = rx.clone().collect();
        h.join().unwrap();
        assert_eq!(all.len(), 1);
        assert!(rx.recv().is_err());
    }
}
