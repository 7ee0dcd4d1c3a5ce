//! GPU (WGSL) vs CPU (rayon mirror) parity of every odometry kernel. Runs on lavapipe in CI:
//! a GPU test, ignored by default (see `rgbid::gpu::test_gpu`).

mod common;

use rgbid::geometry::Se3;
use rgbid::odometry::cpu::{self, CpuPyramid};
use rgbid::odometry::gpu::GpuOdometry;
use rgbid::odometry::kernel::{FilterParams, WarpParams, INVALID_RESIDUAL};

fn params(w: u32, h: u32, off: u32, level: usize, pose: &Se3, est: u32, param: u32) -> WarpParams {
    let s = 0.5f32.powi(level as i32);
    let mut p = WarpParams {
        dims: [w, h, off, (w * h).min(19200)],
        intr: [
            525.0 * s,
            525.0 * s,
            (319.5 + 0.5) * s - 0.5,
            (239.5 + 0.5) * s - 0.5,
        ],
        rot: [[0.0; 4]; 3],
        robust: [6.0, 0.004, 4.0, 3.0],
        flags: [est, 3, param, 0],
    };
    p.set_pose(pose);
    p
}

#[test]
#[ignore = "needs a GPU adapter"]
fn gpu_matches_cpu_mirror() {
    let Some(ctx) = rgbid::gpu::test_gpu("gpu_matches_cpu_mirror") else {
        return;
    };
    // An odd size on purpose: levels of 321x241 -> 160x120 -> 80x60.
    let (w, h) = (321usize, 241usize);
    let a = common::textured_frame(w, h, 1);
    let b = common::textured_frame(w, h, 2);
    // Both reductions: subgroup partials (where the device has subgroups) and the
    // shared-memory fallback.
    for subgroups in [true, false] {
        let mut g = GpuOdometry::with_reduction(ctx.clone(), subgroups).expect("pipelines");
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
        // gradients, filtered value), on levels 0 and 1.
        for level in 0..2 {
            let l = ca.levels[level];
            let f = FilterParams::new(l.width, l.height, l.offset, 4.0, 0.004);
            let cf = ca.filtered_level(level, &f, None);
            let gf = g
                .filtered_level(&ga, level, &f, None)
                .expect("gpu filtered level");
            let (photo, geo) = g.read_pyramid(&gf).expect("read back");
            let mut worst = 0.0f32;
            let mut smoothed = 0usize;
            for k in l.offset..l.offset + l.width * l.height {
                for c in 0..4 {
                    worst = worst
                        .max((photo[k][c] - cf.photo[k][c]).abs() / (1.0 + cf.photo[k][c].abs()));
                    worst =
                        worst.max((geo[k][c] - cf.geo[k][c]).abs() / (1.0 + cf.geo[k][c].abs()));
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
            // param: bit 0 depth parametrisation, bit 1 first-order inverse-depth sampling.
            for (est, param) in [(3u32, 0u32), (1, 1), (2, 0), (0, 0), (3, 2), (2, 3)] {
                let p = params(
                    l.width as u32,
                    l.height as u32,
                    l.offset as u32,
                    level,
                    &pose,
                    est,
                    param,
                );
                // Residual samples.
                let sc = cpu::sample_residuals(&p, &ca, &cb, level);
                let sg = g.sample_residuals(&p, &ga, &gb).expect("gpu sample");
                assert_eq!(sc.len(), sg.len());
                let mut valid = 0;
                for (x, y) in sc.iter().zip(&sg) {
                    for c in 0..2 {
                        assert_eq!(
                            x[c] == INVALID_RESIDUAL,
                            y[c] == INVALID_RESIDUAL,
                            "validity differs"
                        );
                        if x[c] != INVALID_RESIDUAL {
                            valid += 1;
                            let tol = if c == 0 { 1e-3 } else { 1e-5 };
                            assert!(
                                (x[c] - y[c]).abs() < tol,
                                "residual {c}: {} vs {}",
                                x[c],
                                y[c]
                            );
                        }
                    }
                }
                assert!(
                    valid > 100,
                    "too few valid residuals ({valid}) to test anything"
                );
                // Normal equations: every pixel counts, so this also catches loop truncation.
                let nc = cpu::normal_equation_partials(&p, &ca, &cb, level, 16);
                let ng = g
                    .normal_equation_partials(&p, &ga, &gb)
                    .expect("gpu normal equations");
                let sum = |v: &[[f32; 30]]| {
                    let mut s = [0.0f64; 30];
                    for part in v {
                        for k in 0..30 {
                            s[k] += f64::from(part[k]);
                        }
                    }
                    s
                };
                let (xc, xg) = (sum(&nc), sum(&ng));
                assert_eq!(xc[28], xg[28], "photometric counts differ at level {level}");
                assert_eq!(xc[29], xg[29], "geometric counts differ at level {level}");
                let scale = xc.iter().take(28).map(|v| v.abs()).fold(0.0, f64::max);
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
                let (nf, sf) = g
                    .normal_equations_and_sample(&p, &ga, &gb)
                    .expect("gpu fused");
                let xf = sum(&nf);
                assert_eq!(xf[28], xg[28], "fused photometric count at level {level}");
                for k in 0..28 {
                    assert!(
                        (xf[k] - xg[k]).abs() <= 1e-6 * scale + 1e-5 * xg[k].abs(),
                        "fused entry {k} at level {level}: {} vs {}",
                        xf[k],
                        xg[k]
                    );
                }
                assert_eq!(sf.len(), sg.len());
                for (f, s) in sf.iter().zip(&sg) {
                    assert_eq!(f, s, "fused sample differs from the separate sample pass");
                }
                let (_, sfc) = cpu::normal_equations_and_sample(&p, &ca, &cb, level, 7);
                assert_eq!(sfc.len(), sc.len());
                for (f, s) in sfc.iter().zip(&sc) {
                    for c in 0..2 {
                        assert!(
                            (f[c] - s[c]).abs() <= 1e-5 * s[c].abs().max(1.0),
                            "cpu fused sample {f:?} vs {s:?}"
                        );
                    }
                }
                // Covisibility counts.
                let cc = cpu::covisibility_counts(&p, &ca, &cb, level);
                let cg = g
                    .covisibility_counts(&p, &ga, &gb)
                    .expect("gpu covisibility");
                assert_eq!(cc.0, cg.0);
                assert!(
                    (cc.1 as i64 - cg.1 as i64).abs() <= 2,
                    "covisible {cc:?} vs {cg:?}"
                );
            }
        }
    }
}
