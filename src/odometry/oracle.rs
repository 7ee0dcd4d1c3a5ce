//! A literal per-pixel transcription of `pixel_terms` and the normal-equation body of
//! `shaders/odometry.wgsl`, for tests only. The production CPU mirror is the row loop of
//! `rows.rs`, restructured for a CPU (precomputed rays, blocked sums, AVX2 lanes); this
//! transcription keeps that restructuring checked on machines without a GPU adapter, where the
//! WGSL parity tests cannot run.

use super::config::{GeometricParam, GeometricSampling, Linearisation};
use super::kernel::{warp_point, Partial, WarpParams, INVALID_GRAD, MIN_DEPTH};
use super::robust::weight;

/// Residuals and Jacobians of one reference pixel.
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct PixelTerms {
    /// Photometric residual `I_cur(w(x)) - I_ref(x)` (intensity levels), if valid.
    pub r_photo: Option<f32>,
    /// Its Jacobian, `[v; w]`: with respect to the left twist of `cur_from_ref`
    /// (`exp(d) cur_from_ref`, current-frame linearisation), or the reference frame's
    /// approximation of the one with respect to its right twist (`cur_from_ref exp(d)`,
    /// [`Linearisation::Reference`]).
    pub j_photo: [f32; 6],
    /// Geometric residual (inverse depth 1/m, or depth m), if valid.
    pub r_geo: Option<f32>,
    /// Its Jacobian.
    pub j_geo: [f32; 6],
}

#[inline]
fn cross(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// Warps reference pixel `i` of the level into the current frame and evaluates the residuals
/// and Jacobians (thesis eq. 6.5-6.13; bilinear intensity, nearest inverse depth), linearised
/// in the current or the reference frame ([`WarpParams::linearisation`]).
/// Mirror of `pixel_terms` in `odometry.wgsl`.
#[inline]
pub(crate) fn pixel_terms(
    p: &WarpParams,
    ref_photo: &[[f32; 4]],
    ref_geo: &[[f32; 4]],
    cur_photo: &[[f32; 4]],
    cur_geo: &[[f32; 4]],
    i: usize,
    want_jacobians: bool,
) -> PixelTerms {
    let mut out = PixelTerms::default();
    let w = p.width as usize;
    let h = p.height as usize;
    let Some(q) = warp_point(p, ref_geo, i) else {
        return out;
    };
    let (fx, fy, cx, cy) = (p.fx, p.fy, p.cx, p.cy);
    if q[2] < MIN_DEPTH {
        return out;
    }
    let reference = p.linearisation == Linearisation::Reference as u32;
    // The reference point X_A and its inverse depth, as `warp_point` computes them.
    let rho_a = ref_geo[i][0];
    let z_a = 1.0 / rho_a;
    let x_a = [
        ((i % w) as f32 - cx) / fx * z_a,
        ((i / w) as f32 - cy) / fy * z_a,
        z_a,
    ];
    let iz = 1.0 / q[2];
    let u = fx * q[0] * iz + cx;
    let v = fy * q[1] * iz + cy;
    if !(u >= 0.0 && v >= 0.0 && u < (w - 1) as f32 && v < (h - 1) as f32) {
        return out;
    }
    let x0 = u.floor();
    let y0 = v.floor();
    let ax = u - x0;
    let ay = v - y0;
    let k = y0 as usize * w + x0 as usize;
    let (p00, p10, p01, p11) = (
        cur_photo[k],
        cur_photo[k + 1],
        cur_photo[k + w],
        cur_photo[k + w + 1],
    );
    let b00 = (1.0 - ax) * (1.0 - ay);
    let b10 = ax * (1.0 - ay);
    let b01 = (1.0 - ax) * ay;
    let b11 = ax * ay;
    let mut c = [0.0f32; 3];
    for (ch, cc) in c.iter_mut().enumerate() {
        *cc = b00 * p00[ch] + b10 * p10[ch] + b01 * p01[ch] + b11 * p11[ch];
    }
    if p.photometric() {
        out.r_photo = Some(c[0] - ref_photo[i][0]);
        if want_jacobians {
            // The gradient and point of the linearisation: the current frame's (bilinear)
            // at the warped point, or the reference pixel's at the reference point.
            let (gx, gy, jq, jiz) = if reference {
                (ref_photo[i][1], ref_photo[i][2], x_a, rho_a)
            } else {
                (c[1], c[2], q, iz)
            };
            let a = gx * fx * jiz;
            let b = gy * fy * jiz;
            let jt = [a, b, -(a * jq[0] + b * jq[1]) * jiz];
            let jr = cross(jq, jt);
            out.j_photo = [jt[0], jt[1], jt[2], jr[0], jr[1], jr[2]];
        }
    }
    if p.geometric_term() {
        let xn = (u + 0.5).floor() as usize;
        let yn = (v + 0.5).floor() as usize;
        let g = cur_geo[yn * w + xn];
        let ga = ref_geo[i];
        if g[0] > 0.0 && g[1] != INVALID_GRAD && (!reference || ga[1] != INVALID_GRAD) {
            let depth_param = p.geometric == GeometricParam::Depth as u32;
            let rho = if p.sampling == GeometricSampling::Linear as u32 {
                g[0] + g[1] * (u - xn as f32) + g[2] * (v - yn as f32)
            } else {
                g[0]
            };
            // `(residual, gradient u, gradient v, optical-axis term, point, inverse depth)`.
            let terms = if reference {
                // W_B*(p): the sample as the point `q / (rho q_z)` of B (on the ray through
                // w(p)), moved into A by `T^-1 = (R^T, -R^T t)`, as inverse depth (or depth).
                let s = 1.0 / (rho * q[2]);
                let r = &p.rot;
                let d = [q[0] * s - r[0][3], q[1] * s - r[1][3], q[2] * s - r[2][3]];
                let za = r[0][2] * d[0] + r[1][2] * d[1] + r[2][2] * d[2];
                (za >= MIN_DEPTH).then(|| {
                    if depth_param {
                        let ig2 = 1.0 / (rho_a * rho_a);
                        (za - z_a, -ga[1] * ig2, -ga[2] * ig2, -1.0, x_a, rho_a)
                    } else {
                        (1.0 / za - rho_a, ga[1], ga[2], rho_a * rho_a, x_a, rho_a)
                    }
                })
            } else if depth_param {
                let ig2 = 1.0 / (rho * rho);
                Some((1.0 / rho - q[2], -g[1] * ig2, -g[2] * ig2, -1.0, q, iz))
            } else {
                Some((rho - iz, g[1], g[2], iz * iz, q, iz))
            };
            if let Some((res, gu, gv, dz, jq, jiz)) = terms {
                out.r_geo = Some(res);
                if want_jacobians {
                    let a = gu * fx * jiz;
                    let b = gv * fy * jiz;
                    let jt = [a, b, -(a * jq[0] + b * jq[1]) * jiz + dz];
                    let jr = cross(jq, jt);
                    out.j_geo = [jt[0], jt[1], jt[2], jr[0], jr[1], jr[2]];
                }
            }
        }
    }
    out
}

/// Adds `wt * J J^T` and `wt * J r` to a partial (mirror of `accumulate` in the WGSL).
#[inline]
fn accumulate(acc: &mut Partial, j: &[f32; 6], r: f32, wt: f32) {
    let mut k = 0;
    for a in 0..6 {
        let wa = wt * j[a];
        for b in a..6 {
            acc.h[k] += wa * j[b];
            k += 1;
        }
    }
    for a in 0..6 {
        acc.g[a] += wt * j[a] * r;
    }
}

/// Accumulates the IRLS normal equations of reference pixel `i` into `acc`.
/// Mirror of the body of `normal_equations` in the WGSL.
#[inline]
pub(crate) fn accumulate_pixel(
    p: &WarpParams,
    ref_photo: &[[f32; 4]],
    ref_geo: &[[f32; 4]],
    cur_photo: &[[f32; 4]],
    cur_geo: &[[f32; 4]],
    i: usize,
    acc: &mut Partial,
) {
    let t = pixel_terms(p, ref_photo, ref_geo, cur_photo, cur_geo, i, true);
    let est = p.estimator;
    if let Some(r) = t.r_photo {
        let r = r - p.mu_photo;
        let s = p.sigma_photo;
        let z = r / s;
        let w = weight(est, z, p.nu_photo) / (s * s);
        accumulate(acc, &t.j_photo, r, w);
        acc.cost += w * r * r;
        acc.n_photo += 1.0;
    }
    if let Some(r) = t.r_geo {
        let r = r - p.mu_geo;
        let s = p.sigma_geo;
        let z = r / s;
        let w = weight(est, z, p.nu_geo) / (s * s);
        accumulate(acc, &t.j_geo, r, w);
        acc.cost += w * r * r;
        acc.n_geo += 1.0;
    }
}
