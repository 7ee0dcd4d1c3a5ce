//! What one [`Slam`](super::Slam) instance holds in memory, by owner: sums of the capacities
//! of its buffers and the sizes of the GPU buffers it allocated, updated by the front-end at
//! every frame and by the back-end at every keyframe, and the peak of their total.

use super::keyframe::Keyframe;

/// Bytes of memory held by the parts of one [`Slam`](super::Slam) instance at one moment.
///
/// Counted: the capacity of the buffers each part keeps between frames (host memory) and the
/// size of the GPU buffers it allocated (`gpu`). Not counted: temporaries that live within one
/// call (e.g. the pyramids of a loop's dense alignment, a segmentation's output), keyframes
/// still in the queue to the back-end, the allocator's own overhead, and what the caller owns
/// (frames, the map and model built from a finished run).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct MemoryBreakdown {
    /// The keyframes (8-bit intensity, half-precision fused inverse depth, 8-bit weights,
    /// 4 bytes per pixel, and 3 more for 8-bit RGB when the input has colour) the back-end
    /// keeps as the map, and the intensity (and colour) of the keyframe the front-end is
    /// building.
    pub keyframes: usize,
    /// Place recognition: the vocabulary tree, the keyframe database (inverted index, stored
    /// bags of words) and every keyframe's description (ORB keypoints, descriptors, 3D points,
    /// bags of words, direct index) with its per-mask feature flags.
    pub place_recognition: usize,
    /// The keyframe pose graph (vertices, edges with their information matrices).
    pub pose_graph: usize,
    /// The back-end's [`Segmenter`](crate::segment::Segmenter) buffers
    /// ([`Segmenter::scratch_bytes`](crate::segment::Segmenter::scratch_bytes); 0 once the
    /// back-end has stopped).
    pub segmenter: usize,
    /// Host memory of the odometry of the front-end (tracking) and of the back-end (loop
    /// refinement): the pyramids kept between frames on the CPU backend.
    pub odometry: usize,
    /// Host memory of keyframe fusion: the fused inverse depth and weights, and the frames
    /// buffered for the next keyframe.
    pub fusion: usize,
    /// Per-frame records, loop records and per-keyframe timings.
    pub records: usize,
    /// GPU buffers allocated by the odometry (pyramids, kernel parameters, partial sums) and
    /// by fusion (the resident keyframe); 0 on the CPU backend.
    pub gpu: usize,
}

impl MemoryBreakdown {
    /// Total bytes, host and GPU.
    pub fn total(&self) -> usize {
        self.host() + self.gpu
    }

    /// Bytes of host memory (everything but [`Self::gpu`]).
    pub fn host(&self) -> usize {
        self.keyframes
            + self.place_recognition
            + self.pose_graph
            + self.segmenter
            + self.odometry
            + self.fusion
            + self.records
    }

    /// Field-wise sum (the front-end's and the back-end's parts).
    fn plus(&self, o: &MemoryBreakdown) -> MemoryBreakdown {
        MemoryBreakdown {
            keyframes: self.keyframes + o.keyframes,
            place_recognition: self.place_recognition + o.place_recognition,
            pose_graph: self.pose_graph + o.pose_graph,
            segmenter: self.segmenter + o.segmenter,
            odometry: self.odometry + o.odometry,
            fusion: self.fusion + o.fusion,
            records: self.records + o.records,
            gpu: self.gpu + o.gpu,
        }
    }
}

/// The memory account of one [`Slam`](super::Slam) instance (bytes; see [`MemoryBreakdown`]
/// for what is counted): what it holds now and its largest total so far.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct MemoryReport {
    /// What the instance holds now: the front-end's parts as of this call, the back-end's as
    /// of its last keyframe (it runs on its own thread).
    pub now: MemoryBreakdown,
    /// The breakdown at the moment the total was largest, over every processed frame and
    /// every back-end keyframe (and `now`).
    pub peak: MemoryBreakdown,
}

impl MemoryReport {
    /// The largest total so far, bytes (`peak.total()`).
    pub fn peak_bytes(&self) -> usize {
        self.peak.total()
    }
}

/// The two halves of the account, each written by its own thread, and the peak of their sum.
#[derive(Debug, Default)]
pub(crate) struct MemoryAccount {
    frontend: MemoryBreakdown,
    backend: MemoryBreakdown,
    peak: MemoryBreakdown,
}

impl MemoryAccount {
    /// The front-end's parts changed.
    pub fn set_frontend(&mut self, parts: MemoryBreakdown) {
        self.frontend = parts;
        self.note_peak();
    }

    /// The back-end's parts changed.
    pub fn set_backend(&mut self, parts: MemoryBreakdown) {
        self.backend = parts;
        self.note_peak();
    }

    fn note_peak(&mut self) {
        let now = self.frontend.plus(&self.backend);
        if now.total() > self.peak.total() {
            self.peak = now;
        }
    }

    /// The report with `frontend` as the front-end's parts now.
    pub fn report_with(&self, frontend: &MemoryBreakdown) -> MemoryReport {
        let now = frontend.plus(&self.backend);
        MemoryReport {
            now,
            peak: if now.total() > self.peak.total() {
                now
            } else {
                self.peak
            },
        }
    }
}

/// Bytes of capacity of `v` (its own allocation, not what its elements own).
pub(crate) fn vec_bytes<T>(v: &Vec<T>) -> usize {
    v.capacity() * std::mem::size_of::<T>()
}

/// Bytes of a keyframe's images.
pub(crate) fn keyframe_bytes(k: &Keyframe) -> usize {
    vec_bytes(&k.intensity)
        + vec_bytes(&k.inverse_depth)
        + vec_bytes(&k.weight)
        + k.colour.as_ref().map_or(0, |c| c.rgb().len())
}
