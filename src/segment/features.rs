//! Per-superjut features: histogram of normals over golden-section-spiral bins, Shannon
//! entropy and neg-entropy (thesis 5.4), planarity, horizontality and the eigen-transform
//! texture response (Targhi et al. 2006).

use nalgebra::{Matrix3, SMatrix, SymmetricEigen, Vector3};
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
/// Bins are sorted by `z`, so only points whose `z` lies within the angular search radius of
/// the query's `z` are examined: exact nearest point, a fraction of the brute-force cost.
#[derive(Clone, Debug)]
pub struct SphereBins {
    points: Vec<[f32; 3]>,
    /// Upper bound of the angular radius (radians) of every Voronoi cell.
    max_radius: f32,
}

impl SphereBins {
    /// Golden-spiral bins with `m >= 1` points.
    pub fn golden(m: usize) -> Self {
        Self::from_points(golden_spiral(m.max(1)))
    }

    /// Bins at arbitrary unit `points` (must be sorted by decreasing `z` for the pruned
    /// search; other orders still give correct results, just without pruning).
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
        Self { points, max_radius }
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

    /// Index of the nearest bin centre to unit vector `n`.
    #[inline]
    pub fn bin(&self, n: [f32; 3]) -> usize {
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
    ys.par_iter()
        .flat_map_iter(|&cy| {
            let mut out = Vec::new();
            let mut x = half;
            while x + (window - half) <= w {
                let mut a = SMatrix::<f64, W, W>::zeros();
                for r in 0..window {
                    let row = (cy - half + r) * w + (x - half);
                    for c in 0..window {
                        a[(r, c)] = f64::from(intensity.data[row + c]);
                    }
                }
                // Singular values = sqrt of eigenvalues of A^T A (only the top-left block is used).
                let ata = a.transpose() * a;
                let eig = SymmetricEigen::new(ata);
                let mut ev: Vec<f64> = eig.eigenvalues.iter().copied().collect();
                ev.sort_by(|p, q| q.total_cmp(p));
                let ev = &ev[..window];
                let s: f64 = ev[first - 1..].iter().map(|&l| l.max(0.0).sqrt()).sum();
                out.push((
                    x as u32,
                    cy as u32,
                    (s / (window - first + 1) as f64) as f32,
                ));
                x += stride;
            }
            out
        })
        .collect()
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
    fn merge(&mut self, o: &Acc) {
        self.count += o.count;
        for k in 0..3 {
            self.sum[k] += o.sum[k];
        }
        for k in 0..6 {
            self.outer[k] += o.outer[k];
        }
        self.horiz += o.horiz;
        self.tex += o.tex;
        self.tex_n += o.tex_n;
    }
}

/// Computes [`Superjut`] features for `count` segments from per-sample labels, unit normals
/// and points (camera frame, metres; samples labelled [`NO_SEGMENT`] are skipped).
///
/// `up` is the unit up direction in the camera frame (e.g. `[0, -1, 0]` for an upright camera,
/// whose y axis points down). `texture` holds `(sample index, response)` pairs.
pub fn superjut_features(
    labels: &[u32],
    normals: &[[f32; 3]],
    points: &[[f32; 3]],
    count: usize,
    bins: &SphereBins,
    up: [f32; 3],
    texture: &[(usize, f32)],
) -> Vec<Superjut> {
    let m = bins.len();
    let chunk = 4096;
    let (hist, mut accs) = labels
        .par_chunks(chunk)
        .enumerate()
        .fold(
            || (vec![0u32; count * m], vec![Acc::new(); count]),
            |(mut hist, mut accs), (ci, ls)| {
                for (j, &l) in ls.iter().enumerate() {
                    if l == NO_SEGMENT || l as usize >= count {
                        continue;
                    }
                    let i = ci * chunk + j;
                    let n = normals[i];
                    let p = points[i];
                    hist[l as usize * m + bins.bin(n)] += 1;
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
                (hist, accs)
            },
        )
        .reduce(
            || (vec![0u32; count * m], vec![Acc::new(); count]),
            |(mut h1, mut a1), (h2, a2)| {
                for (x, y) in h1.iter_mut().zip(&h2) {
                    *x += y;
                }
                for (x, y) in a1.iter_mut().zip(&a2) {
                    x.merge(y);
                }
                (h1, a1)
            },
        );
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
