//! Per-superjut features: histogram of normals over golden-section-spiral bins, Shannon
//! entropy and neg-entropy (thesis 5.4), planarity, horizontality and the eigen-transform
//! texture response (Targhi et al. 2006).

use nalgebra::{Matrix3, SymmetricEigen, Vector3};
use rayon::prelude::*;

use super::graph::NO_SEGMENT;
use crate::image::ImageF32;

/// `M` points on the unit sphere along the golden-section spiral: `z_k = 1 - (2k+1)/M`,
/// azimuth `k * pi (3 - sqrt 5)`. Their nearest-point (Voronoi) cells have near-equal areas.
pub fn golden_spiral(m: usize) -> Vec<[f32; 3]> {
    let ga = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    (0..m)
        .map(|k| {
            let z = 1.0 - (2.0 * k as f64 + 1.0) / m as f64;
            let r = (1.0 - z * z).max(0.0).sqrt();
            let phi = ga * k as f64;
            [(r * phi.cos()) as f32, (r * phi.sin()) as f32, z as f32]
        })
        .collect()
}

/// Nearest-point binning of unit vectors onto a set of sphere points.
///
/// A unit vector is looked up in a cube map of the sphere (6 faces of
/// `CUBE_GRID x CUBE_GRID` cells): each cell lists, in index order, the only bins that
/// can be nearest to a direction inside it, so a query costs a few dot products and returns
/// exactly what a brute-force search would (the lowest index among exact ties). Other vectors
/// (not of unit length, or not finite) use a search pruned by `z`: bins are sorted by `z`, so
/// only points whose `z` lies within the angular search radius of the query's `z` are examined.
#[derive(Clone, Debug)]
pub struct SphereBins {
    points: Vec<[f32; 3]>,
    /// Upper bound of the angular radius (radians) of every Voronoi cell.
    max_radius: f32,
    /// Entries per cube-map cell in `cell_bins`: the longest candidate list.
    cell_width: usize,
    /// The x, y, z of every entry of `cell_bins`, for [`Self::bin_many`]'s gathers.
    cell_xyz: [Vec<f32>; 3],
    /// The length of every cube-map cell's candidate list (without padding).
    cell_len: Vec<i32>,
    /// Candidate bins of every cube-map cell, in increasing index order, `cell_width` per
    /// cell: a shorter list is padded by repeating its first bin (which never wins over
    /// itself), so every query runs the same loop without a data-dependent branch.
    cell_bins: Vec<u32>,
}

/// Cells per side of each cube-map face of [`SphereBins`].
pub const CUBE_GRID: usize = 16;

/// Angular margin (radians) of the cube-map candidate lists: far above f32 rounding (a bin
/// left out is at least this much farther than the nearest one, so its dot product is
/// smaller by more than `margin^2 / 2 = 5e-5`, ~100x the rounding error of a dot product).
const CUBE_MARGIN: f64 = 0.01;

/// The cube face (`2 * axis + negative`) and cell coordinates `(u, v)` in `[-1, 1]` of a
/// direction with a non-zero component.
#[inline]
fn cube_coords(n: [f32; 3]) -> (usize, f32, f32) {
    let (ax, ay, az) = (n[0].abs(), n[1].abs(), n[2].abs());
    let axis = if ax >= ay && ax >= az {
        0
    } else if ay >= az {
        1
    } else {
        2
    };
    let d = n[axis].abs();
    let face = 2 * axis + usize::from(n[axis] < 0.0);
    (face, n[(axis + 1) % 3] / d, n[(axis + 2) % 3] / d)
}

/// The direction (not normalised) of cube-face coordinates `(u, v)` on `face`.
fn cube_direction(face: usize, u: f64, v: f64) -> [f64; 3] {
    let axis = face / 2;
    let mut d = [0.0; 3];
    d[axis] = if face.is_multiple_of(2) { 1.0 } else { -1.0 };
    d[(axis + 1) % 3] = u;
    d[(axis + 2) % 3] = v;
    let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    [d[0] / l, d[1] / l, d[2] / l]
}

#[inline]
fn cube_cell(u: f32) -> usize {
    (((u + 1.0) * (0.5 * CUBE_GRID as f32)) as usize).min(CUBE_GRID - 1)
}

impl SphereBins {
    /// Golden-spiral bins with `m >= 1` points.
    pub fn golden(m: usize) -> Self {
        Self::from_points(golden_spiral(m.max(1)))
    }

    /// Bins at arbitrary unit `points` (sorted by decreasing `z`, the pruned search of
    /// non-unit queries is faster; other orders still give correct results).
    pub fn from_points(points: Vec<[f32; 3]>) -> Self {
        // Covering radius: estimate by dense sampling, then add margin.
        let probe = golden_spiral(4_000);
        let mut max_radius = 0.0f32;
        for q in &probe {
            let best = points.iter().map(|p| dot(*p, *q)).fold(-2.0f32, f32::max);
            max_radius = max_radius.max(best.clamp(-1.0, 1.0).acos());
        }
        let sorted = points.windows(2).all(|w| w[0][2] >= w[1][2]);
        let max_radius = if sorted {
            (max_radius * 1.5 + 0.02).min(std::f32::consts::PI)
        } else {
            std::f32::consts::PI
        };
        let (cell_start, list) = cube_candidates(&points);
        let cell_width = cell_start
            .windows(2)
            .map(|w| (w[1] - w[0]) as usize)
            .max()
            .unwrap_or(0);
        let mut cell_bins = Vec::with_capacity(cell_width * cell_start.len());
        for w in cell_start.windows(2) {
            let cands = &list[w[0] as usize..w[1] as usize];
            cell_bins.extend_from_slice(cands);
            let pad = cands.first().copied().unwrap_or(0);
            cell_bins.extend(std::iter::repeat_n(pad, cell_width - cands.len()));
        }
        let cell_xyz =
            [0, 1, 2].map(|c| cell_bins.iter().map(|&k| points[k as usize][c]).collect());
        let cell_len = cell_start
            .windows(2)
            .map(|w| (w[1] - w[0]) as i32)
            .collect();
        Self {
            points,
            max_radius,
            cell_width,
            cell_xyz,
            cell_len,
            cell_bins,
        }
    }

    /// Bytes of heap memory the bins hold (their points and cube-map tables).
    pub(crate) fn heap_bytes(&self) -> usize {
        use crate::segment::vec_bytes;
        vec_bytes(&self.points)
            + self.cell_xyz.iter().map(vec_bytes).sum::<usize>()
            + vec_bytes(&self.cell_len)
            + vec_bytes(&self.cell_bins)
    }

    /// Number of bins.
    pub fn len(&self) -> usize {
        self.points.len()
    }

    /// True when there are no bins.
    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// The bin centres (unit vectors).
    pub fn points(&self) -> &[[f32; 3]] {
        &self.points
    }

    /// Index of the nearest bin centre to unit vector `n` (the largest dot product; the lowest
    /// index among exact ties; 0 when there are no bins). Vectors not of unit length take the
    /// search pruned by `z` (a NaN component gives 0).
    #[inline]
    pub fn bin(&self, n: [f32; 3]) -> usize {
        let l2 = dot(n, n);
        if !(l2 > 0.999 && l2 < 1.001) {
            return self.bin_pruned(n);
        }
        let (face, u, v) = cube_coords(n);
        let cell = (face * CUBE_GRID + cube_cell(u)) * CUBE_GRID + cube_cell(v);
        let w = self.cell_width;
        let Some(cands) = self.cell_bins.get(cell * w..(cell + 1) * w) else {
            return 0;
        };
        let mut best = 0usize;
        let mut best_d = f32::NEG_INFINITY;
        for &k in cands {
            let d = dot(self.points[k as usize], n);
            if d > best_d {
                best_d = d;
                best = k as usize;
            }
        }
        best
    }

    /// [`Self::bin`] of many vectors: `out[i]` is the bin of `normals[i]` where `wanted(i)`,
    /// and 0 elsewhere (those vectors are not looked at). The same results as [`Self::bin`]
    /// (the same floating-point operations); with AVX2 (chosen at run time) eight unit
    /// vectors are binned at once, the others go through [`Self::bin`]. Only the first
    /// `min(normals.len(), out.len())` entries are written.
    pub fn bin_many(&self, normals: &[[f32; 3]], wanted: impl Fn(usize) -> bool, out: &mut [u32]) {
        #[cfg(target_arch = "x86_64")]
        {
            if std::is_x86_feature_detected!("avx2") {
                // SAFETY: the CPU supports the feature enabled on `bin_many_avx2`.
                unsafe { self.bin_many_avx2(normals, &wanted, out) };
                return;
            }
        }
        self.bin_many_scalar(normals, &wanted, out);
    }

    /// [`Self::bin_many`] one vector at a time, through [`Self::bin`].
    fn bin_many_scalar(
        &self,
        normals: &[[f32; 3]],
        wanted: &impl Fn(usize) -> bool,
        out: &mut [u32],
    ) {
        for (i, (o, &n)) in out.iter_mut().zip(normals).enumerate() {
            *o = if wanted(i) { self.bin(n) as u32 } else { 0 };
        }
    }

    /// [`Self::bin_many`] eight vectors at a time: the cube-map cell by the operations of
    /// [`cube_coords`] and [`cube_cell`] in lanes, then the cell's padded candidate list
    /// gathered in lanes and searched as [`Self::bin`] does (each dot product as there, as
    /// separate multiplies and adds, so the same values; the first largest wins).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn bin_many_avx2(
        &self,
        normals: &[[f32; 3]],
        wanted: &impl Fn(usize) -> bool,
        out: &mut [u32],
    ) {
        use std::arch::x86_64::*;
        let n = normals.len().min(out.len());
        let (w, m) = (self.cell_width, self.points.len());
        let cells = 6 * CUBE_GRID * CUBE_GRID;
        let xyz = &self.cell_xyz;
        if w == 0
            || m == 0
            || self.cell_bins.len() < cells * w
            || xyz.iter().any(|c| c.len() < cells * w)
            || self.cell_len.len() < cells
        {
            self.bin_many_scalar(normals, wanted, out);
            return;
        }
        let g = CUBE_GRID as i32;
        let mut i = 0;
        while i + 8 <= n {
            // Lanes not wanted look up a unit vector, and give 0 below.
            let mut c = [[0f32; 8]; 3];
            let mut want = 0u32;
            for l in 0..8 {
                let v = if wanted(i + l) {
                    want |= 1 << l;
                    normals[i + l]
                } else {
                    [0.0, 0.0, 1.0]
                };
                for (cc, vv) in c.iter_mut().zip(v) {
                    cc[l] = vv;
                }
            }
            // SAFETY: the loads read 8 floats of 8-float arrays.
            let (x, y, z) = unsafe {
                (
                    _mm256_loadu_ps(c[0].as_ptr()),
                    _mm256_loadu_ps(c[1].as_ptr()),
                    _mm256_loadu_ps(c[2].as_ptr()),
                )
            };
            let l2 = _mm256_add_ps(
                _mm256_add_ps(_mm256_mul_ps(x, x), _mm256_mul_ps(y, y)),
                _mm256_mul_ps(z, z),
            );
            let unit = _mm256_and_ps(
                _mm256_cmp_ps::<_CMP_GT_OQ>(l2, _mm256_set1_ps(0.999)),
                _mm256_cmp_ps::<_CMP_LT_OQ>(l2, _mm256_set1_ps(1.001)),
            );
            let unit_bits = _mm256_movemask_ps(unit) as u32;
            let abs = _mm256_castsi256_ps(_mm256_set1_epi32(0x7fff_ffff));
            let (ax, ay, az) = (
                _mm256_and_ps(x, abs),
                _mm256_and_ps(y, abs),
                _mm256_and_ps(z, abs),
            );
            // Major axis: x where ax >= ay and ax >= az, else y where ay >= az, else z.
            let xm = _mm256_and_ps(
                _mm256_cmp_ps::<_CMP_GE_OQ>(ax, ay),
                _mm256_cmp_ps::<_CMP_GE_OQ>(ax, az),
            );
            let ym = _mm256_andnot_ps(xm, _mm256_cmp_ps::<_CMP_GE_OQ>(ay, az));
            let pick = |a: __m256, b: __m256, cc: __m256| {
                _mm256_blendv_ps(_mm256_blendv_ps(cc, b, ym), a, xm)
            };
            let major = pick(x, y, z);
            // The components after the major axis, cyclically ((axis + 1) % 3, (axis + 2) % 3).
            let (u_num, v_num) = (pick(y, z, x), pick(z, x, y));
            let d = _mm256_and_ps(major, abs);
            let cell_of = |num: __m256| {
                let t = _mm256_mul_ps(
                    _mm256_add_ps(_mm256_div_ps(num, d), _mm256_set1_ps(1.0)),
                    _mm256_set1_ps(0.5 * CUBE_GRID as f32),
                );
                // Truncation as `as usize`, clamped to the grid (NaN lanes, only for vectors
                // that are not unit and go through `bin`, land in cell 0).
                _mm256_min_epi32(
                    _mm256_max_epi32(_mm256_cvttps_epi32(t), _mm256_setzero_si256()),
                    _mm256_set1_epi32(g - 1),
                )
            };
            let (cu, cv) = (cell_of(u_num), cell_of(v_num));
            let axis = _mm256_blendv_epi8(
                _mm256_blendv_epi8(
                    _mm256_set1_epi32(2),
                    _mm256_set1_epi32(1),
                    _mm256_castps_si256(ym),
                ),
                _mm256_setzero_si256(),
                _mm256_castps_si256(xm),
            );
            let neg = _mm256_and_si256(
                _mm256_castps_si256(_mm256_cmp_ps::<_CMP_LT_OQ>(major, _mm256_setzero_ps())),
                _mm256_set1_epi32(1),
            );
            let face = _mm256_add_epi32(_mm256_add_epi32(axis, axis), neg);
            let g_v = _mm256_set1_epi32(g);
            let cell = _mm256_add_epi32(
                _mm256_mullo_epi32(_mm256_add_epi32(_mm256_mullo_epi32(face, g_v), cu), g_v),
                cv,
            );
            let base = _mm256_mullo_epi32(cell, _mm256_set1_epi32(w as i32));
            let mut best = _mm256_setzero_si256();
            let mut best_d = _mm256_set1_ps(f32::NEG_INFINITY);
            // Rounds up to the longest list among the lanes (padding repeats a list's
            // first entry, which never wins again).
            // SAFETY: `cell` < 6 * CUBE_GRID^2 <= cell_len.len() (clamped to the grid).
            let lens = unsafe { _mm256_i32gather_epi32::<4>(self.cell_len.as_ptr(), cell) };
            let mut l8 = [0i32; 8];
            // SAFETY: stores 8 i32 into an 8-i32 array.
            unsafe { _mm256_storeu_si256(l8.as_mut_ptr().cast(), lens) };
            let rounds = (l8.iter().copied().max().unwrap_or(0).max(1) as usize).min(w);
            for j in 0..rounds {
                let idx = _mm256_add_epi32(base, _mm256_set1_epi32(j as i32));
                // SAFETY: `idx` < 6 * CUBE_GRID^2 * w <= the length of cell_bins and of
                // each cell_xyz (checked above; cells clamped to the grid, j < w).
                let (k, dd) = unsafe {
                    let k = _mm256_i32gather_epi32::<4>(self.cell_bins.as_ptr().cast(), idx);
                    let px = _mm256_i32gather_ps::<4>(xyz[0].as_ptr(), idx);
                    let py = _mm256_i32gather_ps::<4>(xyz[1].as_ptr(), idx);
                    let pz = _mm256_i32gather_ps::<4>(xyz[2].as_ptr(), idx);
                    let dd = _mm256_add_ps(
                        _mm256_add_ps(_mm256_mul_ps(px, x), _mm256_mul_ps(py, y)),
                        _mm256_mul_ps(pz, z),
                    );
                    (k, dd)
                };
                let better = _mm256_cmp_ps::<_CMP_GT_OQ>(dd, best_d);
                best = _mm256_blendv_epi8(best, k, _mm256_castps_si256(better));
                best_d = _mm256_blendv_ps(best_d, dd, better);
            }
            let mut lanes = [0u32; 8];
            // SAFETY: stores 8 u32 into an 8-u32 array.
            unsafe { _mm256_storeu_si256(lanes.as_mut_ptr().cast(), best) };
            for (l, &b) in lanes.iter().enumerate() {
                out[i + l] = if want >> l & 1 == 0 {
                    0
                } else if unit_bits >> l & 1 == 1 {
                    b
                } else {
                    self.bin(normals[i + l]) as u32
                };
            }
            i += 8;
        }
        self.bin_many_scalar(&normals[i..n], &|j| wanted(i + j), &mut out[i..n]);
    }

    /// [`Self::bin`] by a search pruned by `z` (exact for unit vectors, given the bins'
    /// covering radius), with a full search as fallback.
    fn bin_pruned(&self, n: [f32; 3]) -> usize {
        let m = self.points.len();
        // z range of candidates: |z_p - z_n| <= sin-free bound via angle: the polar angle of
        // the nearest point differs by at most max_radius.
        let theta = n[2].clamp(-1.0, 1.0).acos();
        let zhi = (theta - self.max_radius).max(0.0).cos();
        let zlo = (theta + self.max_radius).min(std::f32::consts::PI).cos();
        // Points have decreasing z: z_k = 1 - (2k+1)/m  ->  k = ((1 - z) m - 1) / 2.
        let kf = |z: f32| ((1.0 - z) * m as f32 - 1.0) * 0.5;
        let (k0, k1) = if self.max_radius >= std::f32::consts::PI {
            (0, m)
        } else {
            (
                (kf(zhi).floor().max(0.0) as usize).min(m),
                ((kf(zlo).ceil() + 1.0).max(0.0) as usize).min(m),
            )
        };
        let mut best = 0usize;
        let mut best_d = f32::NEG_INFINITY;
        for (k, p) in self.points[k0..k1].iter().enumerate() {
            let d = dot(*p, n);
            if d > best_d {
                best_d = d;
                best = k0 + k;
            }
        }
        if best_d == f32::NEG_INFINITY {
            // Not reachable for unit vectors; fall back to the full search.
            for (k, p) in self.points.iter().enumerate() {
                let d = dot(*p, n);
                if d > best_d {
                    best_d = d;
                    best = k;
                }
            }
        }
        best
    }
}

/// Candidate lists of the cube-map cells: for a cell with centre direction `c` and angular
/// radius `r` (to its farthest corner), every direction `q` in it has its nearest bin within
/// `d(c, b_c) + r` (`b_c` nearest to `c`), so only bins `b` with `d(c, b) <= d(c, b_c) + 2r`
/// can be nearest to `q`; the list keeps those (plus [`CUBE_MARGIN`]) in index order.
fn cube_candidates(points: &[[f32; 3]]) -> (Vec<u32>, Vec<u32>) {
    let cells = 6 * CUBE_GRID * CUBE_GRID;
    let mut start = Vec::with_capacity(cells + 1);
    let mut list = Vec::new();
    let pts: Vec<[f64; 3]> = points
        .iter()
        .map(|p| [f64::from(p[0]), f64::from(p[1]), f64::from(p[2])])
        .collect();
    let dot64 = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let g = CUBE_GRID as f64;
    let at = |i: usize| -1.0 + 2.0 * i as f64 / g;
    for face in 0..6 {
        for iu in 0..CUBE_GRID {
            for iv in 0..CUBE_GRID {
                start.push(list.len() as u32);
                let c = cube_direction(
                    face,
                    0.5 * (at(iu) + at(iu + 1)),
                    0.5 * (at(iv) + at(iv + 1)),
                );
                let r = [(iu, iv), (iu + 1, iv), (iu, iv + 1), (iu + 1, iv + 1)]
                    .iter()
                    .map(|&(a, b)| {
                        dot64(c, cube_direction(face, at(a), at(b)))
                            .clamp(-1.0, 1.0)
                            .acos()
                    })
                    .fold(0.0f64, f64::max);
                let dc = pts
                    .iter()
                    .map(|&p| dot64(c, p))
                    .fold(-2.0f64, f64::max)
                    .clamp(-1.0, 1.0)
                    .acos();
                let reach = dc + 2.0 * r + CUBE_MARGIN;
                let min_dot = if reach >= std::f64::consts::PI {
                    f64::NEG_INFINITY
                } else {
                    reach.cos()
                };
                list.extend(
                    (0..pts.len() as u32).filter(|&k| dot64(c, pts[k as usize]) >= min_dot),
                );
            }
        }
    }
    start.push(list.len() as u32);
    (start, list)
}

#[inline]
fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// Shannon entropy (nats) of a histogram; 0 for an empty one.
pub fn entropy(hist: &[u32]) -> f64 {
    let total: u64 = hist.iter().map(|&c| u64::from(c)).sum();
    if total == 0 {
        return 0.0;
    }
    let t = total as f64;
    hist.iter()
        .filter(|&&c| c > 0)
        .map(|&c| {
            let p = f64::from(c) / t;
            -p * p.ln()
        })
        .sum()
}

/// Normalised neg-entropy `1 - H / ln M` in `[0, 1]`: 1 for all normals in one bin (a
/// plane), 0 for a uniform spread over all `M` bins.
pub fn neg_entropy(hist: &[u32]) -> f64 {
    if hist.len() < 2 {
        return 1.0;
    }
    (1.0 - entropy(hist) / (hist.len() as f64).ln()).clamp(0.0, 1.0)
}

/// Eigen-transform texture response (Targhi, Geusebroek, Zisserman 2006) on a grid.
///
/// For the `window x window` block of intensities (in `[0, 255]`) centred at every
/// `stride`-th pixel, the response is the mean of the singular values `sigma_l..sigma_w`
/// (sorted decreasing, 1-based `l = first`): large on fine texture, near zero on smooth
/// regions. Returned as `(x, y, response)` samples (intensity units).
pub fn eigen_transform_samples(
    intensity: &ImageF32,
    window: usize,
    first: usize,
    stride: usize,
) -> Vec<(u32, u32, f32)> {
    const W: usize = 8;
    let (w, h) = (intensity.width, intensity.height);
    let window = window.clamp(2, W);
    let first = first.clamp(1, window);
    let stride = stride.max(1);
    if w < window || h < window {
        return Vec::new();
    }
    let half = window / 2;
    let ys: Vec<usize> = (half..=h - (window - half)).step_by(stride).collect();
    let xs: Vec<usize> = (half..=w - (window - half)).step_by(stride).collect();
    let response = |ev: &[f64; W]| {
        let mut ev = *ev;
        ev.sort_by(|p, q| q.total_cmp(p));
        let s: f64 = ev[first - 1..window]
            .iter()
            .map(|&l| l.max(0.0).sqrt())
            .sum();
        (s / (window - first + 1) as f64) as f32
    };
    ys.par_iter()
        .flat_map_iter(|&cy| {
            let mut out = Vec::with_capacity(xs.len());
            // Four windows at a time, one per lane (the last group repeats its last window).
            for group in xs.chunks(LANES) {
                let mut g = [[[0.0f64; LANES]; W]; W];
                for lane in 0..LANES {
                    let x = group[lane.min(group.len() - 1)];
                    let mut a = [[0.0f64; W]; W];
                    for (r, ar) in a.iter_mut().enumerate().take(window) {
                        let row = (cy - half + r) * w + (x - half);
                        for (c, v) in ar.iter_mut().enumerate().take(window) {
                            *v = f64::from(intensity.data[row + c]);
                        }
                    }
                    // Singular values = sqrt of the eigenvalues of A^T A (zero-padded to 8x8).
                    for i in 0..W {
                        for j in 0..=i {
                            let v: f64 = (0..window).map(|r| a[r][i] * a[r][j]).sum();
                            g[i][j][lane] = v;
                            g[j][i][lane] = v;
                        }
                    }
                }
                let ev = jacobi_eigenvalues(&mut g);
                for (lane, &x) in group.iter().enumerate() {
                    out.push((x as u32, cy as u32, response(&ev[lane])));
                }
            }
            out
        })
        .collect()
}

/// Matrices solved together by [`jacobi_eigenvalues`], one per lane.
const LANES: usize = 4;
/// Jacobi sweeps: the eigenvalues of 8 x 8 Gram matrices of intensity windows and of random
/// symmetric matrices match nalgebra's to 1e-12 of the largest after 5 (not after 4); one
/// more for margin.
const JACOBI_SWEEPS: usize = 6;

/// Eigenvalues of `LANES` symmetric 8 x 8 matrices at once (`s[i][j][lane]`; overwritten):
/// cyclic Jacobi in round-robin order (the four rotations of a round act on disjoint index
/// pairs, so their angles are independent), a fixed number of sweeps, no branches on the
/// data: the lanes vectorise. Returns the diagonal after the sweeps, per lane.
fn jacobi_eigenvalues(s: &mut [[[f64; LANES]; 8]; 8]) -> [[f64; 8]; LANES] {
    #[cfg(target_arch = "x86_64")]
    {
        if std::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports the feature enabled on `jacobi_avx2`.
            return unsafe { jacobi_avx2(s) };
        }
    }
    jacobi_body(s)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn jacobi_avx2(s: &mut [[[f64; LANES]; 8]; 8]) -> [[f64; 8]; LANES] {
    jacobi_body(s)
}

#[inline(always)]
fn jacobi_body(s: &mut [[[f64; LANES]; 8]; 8]) -> [[f64; 8]; LANES] {
    for _ in 0..JACOBI_SWEEPS {
        for round in 0..7 {
            // Circle method: 7 fixed, the others paired around the circle.
            let mut pairs = [(0usize, 0usize); 4];
            pairs[0] = (round, 7);
            for (k, pair) in pairs.iter_mut().enumerate().skip(1) {
                let a = (round + k) % 7;
                let b = (round + 7 - k) % 7;
                *pair = (a.min(b), a.max(b));
            }
            let mut cs = [[[0.0f64; LANES]; 3]; 4];
            for (r, &(p, q)) in pairs.iter().enumerate() {
                for l in 0..LANES {
                    let apq = s[p][q][l];
                    let theta = (s[q][q][l] - s[p][p][l]) / (2.0 * apq);
                    // theta = +-inf (apq negligible) gives t = 0; apq = 0 may give NaN: 0.
                    let t = (1.0 / (theta.abs() + (theta * theta + 1.0).sqrt())).copysign(theta);
                    let t = if apq != 0.0 { t } else { 0.0 };
                    let c = 1.0 / (t * t + 1.0).sqrt();
                    cs[r][0][l] = c;
                    cs[r][1][l] = t * c;
                    cs[r][2][l] = t;
                }
            }
            for (r, &(p, q)) in pairs.iter().enumerate() {
                let [c, sn, t] = cs[r];
                for k in 0..8 {
                    if k == p || k == q {
                        continue;
                    }
                    for l in 0..LANES {
                        let (kp, kq) = (s[k][p][l], s[k][q][l]);
                        let nkp = c[l] * kp - sn[l] * kq;
                        let nkq = sn[l] * kp + c[l] * kq;
                        s[k][p][l] = nkp;
                        s[p][k][l] = nkp;
                        s[k][q][l] = nkq;
                        s[q][k][l] = nkq;
                    }
                }
                for l in 0..LANES {
                    let apq = s[p][q][l];
                    s[p][p][l] -= t[l] * apq;
                    s[q][q][l] += t[l] * apq;
                    s[p][q][l] = 0.0;
                    s[q][p][l] = 0.0;
                }
            }
        }
    }
    let mut out = [[0.0f64; 8]; LANES];
    for (l, o) in out.iter_mut().enumerate() {
        for (i, v) in o.iter_mut().enumerate() {
            *v = s[i][i][l];
        }
    }
    out
}

/// Per-superjut features. Positions are in the camera frame (x right, y down, z forward), metres.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Superjut {
    /// Segment label (index into the segment list, value in the label image).
    pub label: u32,
    /// Number of pixels (or mesh vertices) with a normal in the segment.
    pub size: usize,
    /// Histogram of normals over the `M` sphere bins (counts).
    pub histogram: Vec<u32>,
    /// Shannon entropy of the normal histogram, nats.
    pub entropy: f64,
    /// Normalised neg-entropy `1 - H/ln M` in `[0, 1]` (1 = planar, 0 = normals everywhere).
    pub neg_entropy: f64,
    /// Planarity `1 - lambda_min / lambda_mid` of the point covariance, in `[0, 1]`
    /// (1 = points on a plane).
    pub planarity: f64,
    /// Mean `|n . up|` over the segment's normals in `[0, 1]` (1 = horizontal surface).
    pub horizontality: f64,
    /// Mean eigen-transform texture response of the samples inside the segment (intensity
    /// units; 0 when no sample falls inside).
    pub texture: f64,
    /// Number of texture samples inside the segment.
    pub texture_samples: usize,
    /// Centroid of the segment's points, metres, camera frame.
    pub centroid: [f64; 3],
    /// Unit normal of the best-fit plane (smallest-eigenvalue eigenvector), facing the camera.
    pub plane_normal: [f64; 3],
}

#[derive(Clone)]
struct Acc {
    count: usize,
    sum: [f64; 3],
    outer: [f64; 6],
    horiz: f64,
    tex: f64,
    tex_n: usize,
}

impl Acc {
    fn new() -> Self {
        Self {
            count: 0,
            sum: [0.0; 3],
            outer: [0.0; 6],
            horiz: 0.0,
            tex: 0.0,
            tex_n: 0,
        }
    }
}

/// Computes [`Superjut`] features for `count` segments from per-sample labels, unit normals
/// and points (camera frame, metres; samples labelled [`NO_SEGMENT`] are skipped).
///
/// `up` is the unit up direction in the camera frame (e.g. `[0, -1, 0]` for an upright camera,
/// whose y axis points down). `texture` holds `(sample index, response)` pairs. Sums run in
/// sample order, so the result does not depend on the number of threads.
pub fn superjut_features(
    labels: &[u32],
    normals: &[[f32; 3]],
    points: &[[f32; 3]],
    count: usize,
    bins: &SphereBins,
    up: [f32; 3],
    texture: &[(usize, f32)],
) -> Vec<Superjut> {
    superjut_features_with(
        labels,
        normals,
        points,
        count,
        bins,
        up,
        texture,
        &mut FeatureScratch::default(),
    )
}

/// The per-sample and per-superjut buffers of [`superjut_features_with`], kept between
/// keyframes by the caller (a [`Segmenter`](crate::segment::Segmenter)) so they reuse memory
/// that is already mapped.
#[derive(Default)]
pub(crate) struct FeatureScratch {
    bin_of: Vec<u32>,
    hist: Vec<u32>,
    accs: Vec<Acc>,
}

impl FeatureScratch {
    /// Bytes of capacity held.
    pub(crate) fn bytes(&self) -> usize {
        use crate::segment::vec_bytes;
        vec_bytes(&self.bin_of) + vec_bytes(&self.hist) + vec_bytes(&self.accs)
    }
}

/// [`superjut_features`] with its buffers in `scratch`; the same results.
#[allow(clippy::too_many_arguments)]
pub(crate) fn superjut_features_with(
    labels: &[u32],
    normals: &[[f32; 3]],
    points: &[[f32; 3]],
    count: usize,
    bins: &SphereBins,
    up: [f32; 3],
    texture: &[(usize, f32)],
    scratch: &mut FeatureScratch,
) -> Vec<Superjut> {
    let m = bins.len();
    let in_range = |l: u32| l != NO_SEGMENT && (l as usize) < count;
    // The bin of every labelled sample (the costly part) in parallel; the sums below in sample
    // order, so every superjut's features are the same whatever the thread count.
    let FeatureScratch { bin_of, hist, accs } = scratch;
    let samples = labels.len().min(normals.len());
    crate::segment::normals::size_for_overwrite(bin_of, samples, 0u32);
    const CHUNK: usize = 4096;
    bin_of
        .par_chunks_mut(CHUNK)
        .zip(labels[..samples].par_chunks(CHUNK))
        .zip(normals[..samples].par_chunks(CHUNK))
        .for_each(|((o, l), n)| bins.bin_many(n, |i| in_range(l[i]), o));
    hist.clear();
    hist.resize(count * m, 0);
    accs.clear();
    accs.resize(count, Acc::new());
    for ((&l, &b), (&n, &p)) in labels.iter().zip(&*bin_of).zip(normals.iter().zip(points)) {
        if !in_range(l) {
            continue;
        }
        hist[l as usize * m + b as usize] += 1;
        let a = &mut accs[l as usize];
        a.count += 1;
        let (x, y, z) = (f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
        a.sum[0] += x;
        a.sum[1] += y;
        a.sum[2] += z;
        a.outer[0] += x * x;
        a.outer[1] += x * y;
        a.outer[2] += x * z;
        a.outer[3] += y * y;
        a.outer[4] += y * z;
        a.outer[5] += z * z;
        a.horiz += f64::from(dot(n, up).abs());
    }
    for &(i, r) in texture {
        if let Some(&l) = labels.get(i) {
            if l != NO_SEGMENT && (l as usize) < count {
                accs[l as usize].tex += f64::from(r);
                accs[l as usize].tex_n += 1;
            }
        }
    }
    (0..count)
        .map(|s| {
            let a = &accs[s];
            let histogram = hist[s * m..(s + 1) * m].to_vec();
            let n = a.count.max(1) as f64;
            let c = [a.sum[0] / n, a.sum[1] / n, a.sum[2] / n];
            let o = a.outer;
            let cov = Matrix3::new(
                o[0] / n - c[0] * c[0],
                o[1] / n - c[0] * c[1],
                o[2] / n - c[0] * c[2],
                o[1] / n - c[0] * c[1],
                o[3] / n - c[1] * c[1],
                o[4] / n - c[1] * c[2],
                o[2] / n - c[0] * c[2],
                o[4] / n - c[1] * c[2],
                o[5] / n - c[2] * c[2],
            );
            let eig = SymmetricEigen::new(cov);
            let mut idx = [0usize, 1, 2];
            idx.sort_by(|&p, &q| eig.eigenvalues[p].total_cmp(&eig.eigenvalues[q]));
            let l0 = eig.eigenvalues[idx[0]].max(0.0);
            let l1 = eig.eigenvalues[idx[1]].max(0.0);
            let planarity = if a.count >= 3 && l1 > 0.0 {
                (1.0 - l0 / l1).clamp(0.0, 1.0)
            } else {
                0.0
            };
            let mut pn: Vector3<f64> = eig.eigenvectors.column(idx[0]).into_owned();
            if pn.dot(&Vector3::new(c[0], c[1], c[2])) > 0.0 {
                pn = -pn;
            }
            Superjut {
                label: s as u32,
                size: a.count,
                entropy: entropy(&histogram),
                neg_entropy: neg_entropy(&histogram),
                histogram,
                planarity,
                horizontality: a.horiz / n,
                texture: if a.tex_n > 0 {
                    a.tex / a.tex_n as f64
                } else {
                    0.0
                },
                texture_samples: a.tex_n,
                centroid: c,
                plane_normal: [pn.x, pn.y, pn.z],
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The lane-parallel Jacobi eigenvalues agree with nalgebra's on random symmetric
    /// matrices and on Gram matrices of intensity windows (rank-deficient, eigenvalues spread
    /// over many decades), to 1e-12 of the largest; padded blocks give zeros.
    #[test]
    fn jacobi_eigenvalues_match_nalgebra() {
        use nalgebra::SMatrix;
        use rand::{Rng, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(5);
        let mut next = || rng.random::<f64>();
        for case in 0..200 {
            let mut g = [[[0.0f64; LANES]; 8]; 8];
            let mut mats = Vec::new();
            for lane in 0..LANES {
                let n = [8usize, 8, 5][(case + lane) % 3];
                let mut a = SMatrix::<f64, 8, 8>::zeros();
                if (case + lane) % 2 == 0 {
                    for i in 0..n {
                        for j in 0..=i {
                            let v = next() * 2.0 - 1.0;
                            a[(i, j)] = v;
                            a[(j, i)] = v;
                        }
                    }
                } else {
                    let mut win = SMatrix::<f64, 8, 8>::zeros();
                    for r in 0..n {
                        for c in 0..n {
                            let edge = if c > 2 + case % 4 { 90.0 } else { 0.0 };
                            win[(r, c)] =
                                120.0 + 2.0 * r as f64 + edge + (case % 7) as f64 * next();
                        }
                    }
                    a = win.transpose() * win;
                }
                for i in 0..8 {
                    for j in 0..8 {
                        g[i][j][lane] = a[(i, j)];
                    }
                }
                mats.push(a);
            }
            let ev = jacobi_eigenvalues(&mut g);
            for (lane, a) in mats.iter().enumerate() {
                let mut want: Vec<f64> = a.symmetric_eigenvalues().iter().copied().collect();
                let mut got = ev[lane].to_vec();
                want.sort_by(f64::total_cmp);
                got.sort_by(f64::total_cmp);
                let scale = want.iter().fold(1e-300f64, |s, v| s.max(v.abs()));
                for (g, w) in got.iter().zip(&want) {
                    assert!(
                        (g - w).abs() <= 1e-12 * scale,
                        "case {case}: {got:?} vs {want:?}"
                    );
                }
            }
        }
    }

    #[test]
    fn pruned_binning_equals_brute_force() {
        let bins = SphereBins::golden(80);
        let probe = golden_spiral(5000);
        for q in probe {
            let brute = (0..80)
                .max_by(|&a, &b| dot(bins.points[a], q).total_cmp(&dot(bins.points[b], q)))
                .unwrap();
            let got = bins.bin(q);
            let (db, dg) = (dot(bins.points[brute], q), dot(bins.points[got], q));
            assert!((db - dg).abs() < 1e-6, "{q:?}: {brute} vs {got}");
        }
    }

    /// The cube-map lookup gives exactly the brute-force nearest bin (lowest index among exact
    /// ties), as does the z-pruned search it replaced; non-unit vectors take the pruned path.
    #[test]
    fn cube_map_binning_equals_brute_force() {
        let brute = |bins: &SphereBins, q: [f32; 3]| {
            let mut best = (0, f32::NEG_INFINITY);
            for (k, p) in bins.points.iter().enumerate() {
                let d = dot(*p, q);
                if d > best.1 {
                    best = (k, d);
                }
            }
            best.0
        };
        let mut s = 0x2545_f491_4f6c_dd1du64;
        let mut uniform = || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
        };
        for m in [2, 7, 80, 300] {
            let bins = SphereBins::golden(m);
            let mut queries: Vec<[f32; 3]> = golden_spiral(20_000);
            // Random directions, and directions on cube-map cell borders and bin midpoints.
            for _ in 0..100_000 {
                let v = [uniform(), uniform(), uniform()];
                let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
                if l > 1e-3 {
                    queries.push([(v[0] / l) as f32, (v[1] / l) as f32, (v[2] / l) as f32]);
                }
            }
            for i in 0..=CUBE_GRID {
                for j in 0..=CUBE_GRID {
                    let (u, v) = (
                        -1.0 + 2.0 * i as f64 / CUBE_GRID as f64,
                        -1.0 + 2.0 * j as f64 / CUBE_GRID as f64,
                    );
                    for face in 0..6 {
                        let d = cube_direction(face, u, v);
                        queries.push([d[0] as f32, d[1] as f32, d[2] as f32]);
                    }
                }
            }
            for p in bins.points.windows(2) {
                let c = [p[0][0] + p[1][0], p[0][1] + p[1][1], p[0][2] + p[1][2]];
                let l = dot(c, c).sqrt();
                if l > 1e-3 {
                    queries.push([c[0] / l, c[1] / l, c[2] / l]);
                }
            }
            for &q in &queries {
                let want = brute(&bins, q);
                assert_eq!(bins.bin(q), want, "m {m} {q:?}");
                assert_eq!(bins.bin_pruned(q), want, "m {m} {q:?} (pruned)");
            }
            // Many at once (eight-lane path and its tail), with vectors that are not unit
            // (scalar fallback per lane) and lanes not wanted mixed in.
            queries.extend([
                [f32::NAN, 0.0, 1.0],
                [0.0; 3],
                [0.0, 0.0, 0.5],
                [3.0, -1.0, 0.2],
                [f32::INFINITY, 0.0, 0.0],
            ]);
            queries.rotate_right(3);
            let wanted = |i: usize| i % 5 != 2;
            let mut out = vec![7u32; queries.len()];
            bins.bin_many(&queries, wanted, &mut out);
            for (i, (&q, &o)) in queries.iter().zip(&out).enumerate() {
                let want = if wanted(i) { bins.bin(q) as u32 } else { 0 };
                assert_eq!(o, want, "m {m} {q:?} (many, index {i})");
            }
            assert_eq!(bins.bin([f32::NAN, 0.0, 1.0]), 0);
            let half = [0.0, 0.0, 0.5];
            assert_eq!(bins.bin(half), bins.bin_pruned(half));
        }
    }

    #[test]
    fn entropy_limits() {
        let mut h = vec![0u32; 80];
        h[3] = 100;
        assert_eq!(entropy(&h), 0.0);
        assert_eq!(neg_entropy(&h), 1.0);
        let u = vec![5u32; 80];
        assert!((entropy(&u) - 80f64.ln()).abs() < 1e-12);
        assert!(neg_entropy(&u).abs() < 1e-12);
    }

    #[test]
    fn eigen_transform_flat_vs_textured() {
        let flat = ImageF32::filled(32, 32, 128.0);
        let mut tex = flat.clone();
        let mut s = 12345u32;
        for v in &mut tex.data {
            s = s.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            *v = (s >> 24) as f32;
        }
        let f: f32 = eigen_transform_samples(&flat, 8, 5, 4)
            .iter()
            .map(|s| s.2)
            .sum();
        let t = eigen_transform_samples(&tex, 8, 5, 4);
        assert!(!t.is_empty());
        let tm: f32 = t.iter().map(|s| s.2).sum::<f32>() / t.len() as f32;
        assert!(f.abs() < 1e-2 * t.len() as f32, "flat {f}");
        assert!(tm > 20.0, "textured {tm}");
    }
}
