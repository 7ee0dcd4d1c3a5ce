//! GPU (WGSL) vs CPU (rayon mirror) parity of every odometry kernel, through the kernel
//! interface: one body runs the kernels of a backend, and the outputs of the two backends are
//! compared. Runs on lavapipe in CI: GPU tests, ignored by default (see `crate::gpu::test_gpu`).

use super::backend::{CpuKernels, Kernels};
use super::cpu::CpuPyramid;
use super::gpu::GpuKernels;
use super::kernel::{Partial, PyrParams, WarpParams, INVALID_RESIDUAL};
use crate::geometry::Se3;
use crate::image::{test_pattern, RgbdFrame};

fn params(
    l: &super::cpu::LevelLayout,
    level: usize,
    pose: &Se3,
    est: u32,
    param: u32,
) -> WarpParams {
    let s = 0.5f32.powi(level as i32);
    let (w, h) = (l.width as u32, l.height as u32);
    let mut p = WarpParams {
        width: w,
        height: h,
        offset: l.offset as u32,
        samples: (w * h).min(19200),
        fx: 525.0 * s,
        fy: 525.0 * s,
        cx: (319.5 + 0.5) * s - 0.5,
        cy: (239.5 + 0.5) * s - 0.5,
        rot: [[0.0; 4]; 3],
        sigma_photo: 6.0,
        sigma_geo: 0.004,
        nu_photo: 4.0,
        nu_geo: 3.0,
        estimator: est,
        terms: 3,
        geometric: param & 1,
        sampling: (param >> 1) & 1,
        occlusion: 0.0,
        // Non-zero locations, so the kernels' centring is compared too.
        mu_photo: 1.5,
        mu_geo: if param & 1 == 1 { 0.004 } else { 0.0008 },
        linearisation: (param >> 2) & 1,
    };
    p.set_pose(pose);
    p
}

/// The 28 sums (h, g, cost) and the two counts of a set of partials, summed in f64.
fn sum(v: &[Partial]) -> ([f64; 28], f64, f64) {
    let mut s = [0.0f64; 28];
    let (mut np, mut ng) = (0.0, 0.0);
    for part in v {
        for (k, x) in part.h.iter().chain(&part.g).chain([&part.cost]).enumerate() {
            s[k] += f64::from(*x);
        }
        np += f64::from(part.n_photo);
        ng += f64::from(part.n_geo);
    }
    (s, np, ng)
}

/// What the warp kernels of one backend give for one level and parameter set.
struct WarpOutputs {
    sample: Vec<[f32; 2]>,
    partials: Vec<Partial>,
    fused_partials: Vec<Partial>,
    fused_sample: Vec<[f32; 2]>,
    counts: (u64, u64),
    /// Covisibility counts with the occlusion test at a tolerance that rejects some pixels.
    counts_occluded: (u64, u64),
}

/// One test body for every backend: the warp kernels on `(a, b)` at `p`.
fn run_warp<K: Kernels>(
    k: &mut K,
    a: &K::Pyramid,
    b: &K::Pyramid,
    p: &WarpParams,
    level: usize,
) -> WarpOutputs {
    let sample = k.sample_residuals(p, a, b, level).expect("sample");
    let partials = k
        .normal_equation_partials(p, a, b, level)
        .expect("normal equations");
    let (fused_partials, fused_sample) = k
        .normal_equations_and_sample(p, a, b, level)
        .expect("fused pass");
    let counts = k.covisibility_counts(p, a, b, level).expect("covisibility");
    let mut po = *p;
    po.occlusion = 3.0 * p.sigma_geo;
    let counts_occluded = k
        .covisibility_counts(&po, a, b, level)
        .expect("covisibility with the occlusion test");
    WarpOutputs {
        sample,
        partials,
        fused_partials,
        fused_sample,
        counts,
        counts_occluded,
    }
}

fn frames() -> (RgbdFrame, RgbdFrame) {
    // An odd size on purpose: levels of 321x241 -> 160x120 -> 80x60.
    (test_pattern(321, 241, 1), test_pattern(321, 241, 2))
}

#[test]
#[ignore = "needs a GPU adapter"]
fn gpu_matches_cpu_mirror() {
    let Some(ctx) = crate::gpu::test_gpu("gpu_matches_cpu_mirror") else {
        return;
    };
    let (a, b) = frames();
    let mut cpu = CpuKernels::new();
    // Both reductions: subgroup partials (where the device has subgroups) and the
    // shared-memory fallback.
    for subgroups in [true, false] {
        let mut g = GpuKernels::with_reduction(ctx.clone(), subgroups).expect("pipelines");
        let (ca, cb) = (CpuPyramid::build(&a, 3), CpuPyramid::build(&b, 3));
        let ga = g.build(&a, 3, None).expect("gpu pyramid");
        let gb = g.build(&b, 3, None).expect("gpu pyramid");

        // A tracker's pyramid: level 0 not written, level 1 downsampled straight from the input,
        // gradients from level 1: levels 1.. equal the CPU pyramid with gradients from level 1.
        {
            let cl = CpuPyramid::build_reusing(&a, 3, 1, None);
            let gl = g
                .build_levels(&a, 3, 1, 1, None)
                .expect("gpu pyramid from level 1");
            let (photo, geo) = g.read_pyramid(&gl).expect("read back");
            let start = cl.levels[1].offset;
            for k in start..photo.len() {
                // .w: the CPU pyramid caches z = 1/rho there.
                for c in 0..3 {
                    assert_eq!(photo[k][c], cl.photo[k][c], "photo {k}.{c} (levels from 1)");
                    assert_eq!(geo[k][c], cl.geo[k][c], "geo {k}.{c} (levels from 1)");
                }
            }
        }

        // Pyramids and gradients.
        let (photo, geo) = g.read_pyramid(&ga).expect("read back");
        assert_eq!(photo.len(), ca.photo.len());
        let mut worst = 0.0f32;
        for k in 0..photo.len() {
            for c in 0..3 {
                worst =
                    worst.max((photo[k][c] - ca.photo[k][c]).abs() / (1.0 + ca.photo[k][c].abs()));
                worst = worst.max((geo[k][c] - ca.geo[k][c]).abs() / (1.0 + ca.geo[k][c].abs()));
            }
        }
        assert!(worst < 1e-5, "pyramid differs by {worst}");

        // The covariance pass's bilateral-filtered level (all four lanes: raw value, filtered
        // gradients, filtered value; the CPU caches z = 1 / rho in geo.w instead, so the
        // GPU's filtered inverse depth is compared with the mirror's filter), on levels 0
        // and 1.
        for level in 0..2 {
            let l = ca.levels[level];
            let f = PyrParams::filter(l.width, l.height, l.offset, 4.0, 0.004);
            let cf = Kernels::filtered_level(&mut cpu, &ca, level, &f, None).expect("cpu");
            let gf = Kernels::filtered_level(&mut g, &ga, level, &f, None).expect("gpu");
            let (photo, geo) = g.read_pyramid(&gf).expect("read back");
            let mut worst = 0.0f32;
            let mut smoothed = 0usize;
            let range = l.offset..l.offset + l.width * l.height;
            let (lp, lg) = (&ca.photo[range.clone()], &ca.geo[range.clone()]);
            for k in range {
                let (x, y) = ((k - l.offset) % l.width, (k - l.offset) / l.width);
                let rhof = crate::odometry::kernel::bilateral(&f, lp, lg, x, y).1;
                let cpu_geo = [cf.geo[k][0], cf.geo[k][1], cf.geo[k][2], rhof];
                let rho = cf.geo[k][0];
                let z = if rho > 0.0 { 1.0 / rho } else { 0.0 };
                assert_eq!(cf.geo[k][3], z, "the CPU's z cache at {k}");
                for c in 0..4 {
                    worst = worst
                        .max((photo[k][c] - cf.photo[k][c]).abs() / (1.0 + cf.photo[k][c].abs()));
                    worst = worst.max((geo[k][c] - cpu_geo[c]).abs() / (1.0 + cpu_geo[c].abs()));
                }
                smoothed += usize::from(cf.photo[k][3] != cf.photo[k][0]);
            }
            assert!(worst < 1e-5, "filtered level {level} differs by {worst}");
            assert!(
                smoothed > l.width * l.height / 2,
                "the filter changed only {smoothed} pixels"
            );
        }

        let pose = Se3::exp(&[0.02, -0.01, 0.03, 0.01, -0.02, 0.005]);
        for level in 0..3 {
            let l = ca.levels[level];
            // param: bit 0 depth parametrisation, bit 1 first-order inverse-depth sampling,
            // bit 2 the reference-frame linearisation.
            for (est, param) in [
                (3u32, 0u32),
                (1, 1),
                (2, 0),
                (0, 0),
                (3, 2),
                (2, 3),
                (3, 4),
                (1, 5),
                (0, 6),
                (2, 7),
            ] {
                let p = params(&l, level, &pose, est, param);
                let c = run_warp(&mut cpu, &ca, &cb, &p, level);
                let o = run_warp(&mut g, &ga, &gb, &p, level);
                // Residual samples.
                assert_eq!(c.sample.len(), o.sample.len());
                let mut valid = 0;
                for (x, y) in c.sample.iter().zip(&o.sample) {
                    for ch in 0..2 {
                        assert_eq!(
                            x[ch] == INVALID_RESIDUAL,
                            y[ch] == INVALID_RESIDUAL,
                            "validity differs"
                        );
                        if x[ch] != INVALID_RESIDUAL {
                            valid += 1;
                            let tol = if ch == 0 { 1e-3 } else { 1e-5 };
                            assert!(
                                (x[ch] - y[ch]).abs() < tol,
                                "residual {ch}: {} vs {}",
                                x[ch],
                                y[ch]
                            );
                        }
                    }
                }
                assert!(
                    valid > 100,
                    "too few valid residuals ({valid}) to test anything"
                );
                // Normal equations: every pixel counts, so this also catches loop truncation.
                let (xc, cnp, cng) = sum(&c.partials);
                let (xg, gnp, gng) = sum(&o.partials);
                assert_eq!(cnp, gnp, "photometric counts differ at level {level}");
                assert_eq!(cng, gng, "geometric counts differ at level {level}");
                let scale = xc.iter().map(|v| v.abs()).fold(0.0, f64::max);
                for k in 0..28 {
                    assert!(
                        (xc[k] - xg[k]).abs() <= 2e-4 * scale + 1e-3 * xc[k].abs(),
                        "entry {k} at level {level} est {est}: cpu {} gpu {}",
                        xc[k],
                        xg[k]
                    );
                }
                // The fused pass (normal equations + the sample in one submission) returns the
                // same partial sums and the same sample as the separate kernels.
                let (xf, fnp, _) = sum(&o.fused_partials);
                assert_eq!(fnp, gnp, "fused photometric count at level {level}");
                for k in 0..28 {
                    assert!(
                        (xf[k] - xg[k]).abs() <= 1e-6 * scale + 1e-5 * xg[k].abs(),
                        "fused entry {k} at level {level}: {} vs {}",
                        xf[k],
                        xg[k]
                    );
                }
                assert_eq!(o.fused_sample.len(), o.sample.len());
                for (f, s) in o.fused_sample.iter().zip(&o.sample) {
                    assert_eq!(f, s, "fused sample differs from the separate sample pass");
                }
                assert_eq!(c.fused_sample.len(), c.sample.len());
                for (f, s) in c.fused_sample.iter().zip(&c.sample) {
                    for ch in 0..2 {
                        assert!(
                            (f[ch] - s[ch]).abs() <= 1e-5 * s[ch].abs().max(1.0),
                            "cpu fused sample {f:?} vs {s:?}"
                        );
                    }
                }
                // Covisibility counts.
                assert_eq!(c.counts.0, o.counts.0);
                assert!(
                    (c.counts.1 as i64 - o.counts.1 as i64).abs() <= 2,
                    "covisible {:?} vs {:?}",
                    c.counts,
                    o.counts
                );
                assert_eq!(c.counts_occluded.0, o.counts_occluded.0);
                assert!(
                    c.counts_occluded.1 < c.counts.1,
                    "the occlusion test rejected nothing: {:?} vs {:?}",
                    c.counts_occluded,
                    c.counts
                );
                assert!(
                    (c.counts_occluded.1 as i64 - o.counts_occluded.1 as i64).abs() <= 2,
                    "covisible with the occlusion test {:?} vs {:?}",
                    c.counts_occluded,
                    o.counts_occluded
                );
            }
        }
    }
}

/// The same frames tracked by the two monomorphised trackers give the same poses (to the
/// kernels' f32 summation order), with either linearisation (the reference one with the
/// bilateral covariance pass, which then filters the reference level).
#[test]
#[ignore = "needs a GPU adapter"]
fn gpu_tracker_matches_cpu_tracker() {
    let Some(ctx) = crate::gpu::test_gpu("gpu_tracker_matches_cpu_tracker") else {
        return;
    };
    let camera = crate::camera::PinholeCamera::new(262.5, 262.5, 159.75, 119.75, 320, 240);
    let variants = [
        super::OdometryConfig::default(),
        super::OdometryConfig {
            linearisation: super::Linearisation::Reference,
            covariance: super::CovarianceGradients::Bilateral,
            ..Default::default()
        },
    ];
    for config in variants {
        let lin = config.linearisation;
        let mut cpu =
            super::tracker::Tracker::new_cpu(config.clone(), camera).expect("cpu tracker");
        let mut gpu =
            super::tracker::Tracker::new_gpu(config, camera, ctx.clone()).expect("gpu tracker");
        let (a, b) = (test_pattern(320, 240, 1), test_pattern(320, 240, 2));
        let pc = cpu.prepare(&a).expect("prepare");
        let qc = cpu.prepare(&b).expect("prepare");
        let pg = gpu.prepare(&a).expect("prepare");
        let qg = gpu.prepare(&b).expect("prepare");
        let ac = cpu
            .align_prepared(&pc, &qc, Se3::IDENTITY)
            .expect("cpu align");
        let ag = gpu
            .align_prepared(&pg, &qg, Se3::IDENTITY)
            .expect("gpu align");
        let d = (ac.cur_from_ref.inverse() * ag.cur_from_ref).log();
        let norm = d.iter().map(|x| x * x).sum::<f64>().sqrt();
        assert!(
            norm < 1e-4,
            "{lin:?}: cpu and gpu alignments differ by {norm}: {d:?}"
        );
        // The covariances (the reference form's through the filtered reference level).
        let (cc, cg) = (
            ac.covariance.expect("cpu covariance"),
            ag.covariance.expect("gpu covariance"),
        );
        for i in 0..6 {
            let (x, y) = (cc.rows()[i][i], cg.rows()[i][i]);
            assert!(
                (x - y).abs() <= 1e-2 * x.abs(),
                "{lin:?}: covariance {i}: cpu {x} gpu {y}"
            );
        }
        let vc = cpu
            .covisibility_prepared(&pc, &qc, &ac.cur_from_ref)
            .expect("cpu");
        let vg = gpu
            .covisibility_prepared(&pg, &qg, &ag.cur_from_ref)
            .expect("gpu");
        assert!((vc - vg).abs() < 1e-3, "{lin:?}: covisibility {vc} vs {vg}");
    }
}
