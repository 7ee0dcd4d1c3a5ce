#!/usr/bin/env python3
"""Renders docs/results.md from the benchmarks' JSON reports in docs/results/*.json.

Every report is what a benchmark writes with `--json FILE` (`rgbid bench odometry`,
`rgbid bench kernels`, `rgbid graph bench`, `python/benchmarks/overhead.py`): a `meta` object (date, commit, command, machine)
and the rows the benchmark printed. One section per report, in file-name order, so the output
depends only on the reports.

It also writes the README's headline table (between `<!-- headline:begin -->` and
`<!-- headline:end -->`) from docs/results/odometry_redkitchen.json.

Usage:
    python3 scripts/results.py            # write docs/results.md and the README headline
    python3 scripts/results.py --check    # exit 1 if either is not what it would write
Standard library only.
"""
import argparse
import difflib
import json
import pathlib
import sys

ROOT = pathlib.Path(__file__).resolve().parent.parent
COMMAND = "python3 scripts/results.py"

PEER_NAMES = {
    "cv_rgbd": "OpenCV `Odometry` RGB_DEPTH",
    "cv_rgb": "OpenCV `Odometry` RGB",
    "cv_icp": "OpenCV `Odometry` DEPTH (ICP)",
    "o3dt_hybrid": "Open3D tensor Hybrid",
    "o3dt_intensity": "Open3D tensor Intensity",
    "o3d_hybrid": "Open3D legacy Hybrid",
    "o3d_color": "Open3D legacy Color",
}
PEER_LIBRARY = {"cv_": "opencv", "o3d": "open3d"}


def num(v, fmt):
    """A number in the given format, '-' for missing or non-finite values."""
    if v is None or isinstance(v, str):
        return "-" if v is None else v
    if v != v or v in (float("inf"), float("-inf")):
        return "-"
    return format(v, fmt)


def table(header, rows):
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return out


def provenance(doc, name):
    m = doc.get("meta", {})
    mach = m.get("machine", {})
    dirty = m.get("dirty")
    commit = "`{}`{}".format(
        m.get("commit", "unknown"),
        " (with uncommitted changes)" if dirty else "" if dirty is False else " (tree state unknown)",
    )
    gpus = ", ".join(mach.get("gpu_adapters") or []) or "none (no GPU backend ran)"
    lines = [
        f"- Report: `docs/results/{name}`",
        f"- Date (UTC): {m.get('date_utc', '?')}; commit {commit}; rgbid {m.get('rgbid_version', '?')}",
        "- Machine: {}, {} logical cores, {}; GPU: {}".format(
            mach.get("cpu", "?"), mach.get("logical_cores", "?"), mach.get("os", "?"), gpus
        ),
        f"- Command: `{m.get('command', '?')}`",
    ]
    load = m.get("load_average")
    if load:
        lines[2] += "; load average {} / {} / {} (1 / 5 / 15 min) when the report was written".format(
            *(num(x, ".2f") for x in load))
    versions = doc.get("peer_versions") or {}
    if versions:
        lines.append("- Peers: " + ", ".join(f"{k} {v}" for k, v in sorted(versions.items())))
    return lines


def method_label(row, versions):
    m = row.get("method", "?")
    if not row.get("peer"):
        return f"**{m}**"
    name = PEER_NAMES.get(m, m)
    for prefix, lib in PEER_LIBRARY.items():
        if m.startswith(prefix) and lib in versions:
            name = name.replace(name.split()[0], f"{name.split()[0]} {versions[lib]}", 1)
    return f"{name} (`{m}`)"


def render_odometry(doc):
    rows = doc.get("rows", [])
    versions = doc.get("peer_versions") or {}
    peers = [r["method"] for r in rows if r.get("peer")]
    out = [
        f"Sequence `{doc.get('sequence_name', '?')}` ({doc.get('sequence_frames', '?')} frames"
        + (f", camera `{doc['camera']}`" if doc.get("camera") else "")
        + "). Accuracy of every row is computed by rgbid's evaluator from the trajectory file "
        "(ATE RMSE after rigid alignment; RPE RMSE over 1 s windows, TUM `evaluate_rpe` "
        "semantics). Times are medians per frame of compute, decoding excluded. Speed-up: the "
        "peer's median time over the row's, measured in the same run.",
        "",
    ]
    header = ["method", "frames", "ATE RMSE m", "RPE m/s", "RPE deg/s", "median ms/frame", "p90 ms"]
    header += [f"speed-up vs `{p}`" for p in peers]
    body = []
    for r in rows:
        cells = [
            method_label(r, versions),
            r.get("frames", "-"),
            num(r.get("ate_rmse_m"), ".4f"),
            num(r.get("rpe_m_per_s"), ".4f"),
            num(r.get("rpe_deg_per_s"), ".3f"),
            num(r.get("ms_median"), ".1f"),
            num(r.get("ms_p90"), ".1f"),
        ]
        for p in peers:
            cells.append("1.00x" if p == r.get("method") else num(r.get("speedup_vs", {}).get(p), ".2f") + "x")
        body.append(cells)
    out += table(header, body)
    staged = [r for r in rows if r.get("stages_ms")]
    if staged:
        out += ["", "Per-stage medians of the rgbid rows (ms per frame) and memory:", ""]
        st_header = ["backend", "pyramid", "scale", "reduce", "solve", "covisibility", "covariance",
                     "decode (not counted)", "resident MiB after 10 frames / end / process peak"]
        st_body = []
        for r in staged:
            s = r["stages_ms"]
            st_body.append([
                r.get("backend") or r.get("method"),
                *(num(s.get(k), ".2f") for k in ("pyramid", "scale", "reduce", "solve", "covisibility", "covariance")),
                num(r.get("decode_ms_median"), ".2f"),
                " / ".join(num(r.get(k), ".0f") for k in ("rss_mib_after_10", "rss_mib_end", "peak_rss_mib")),
            ])
        out += table(st_header, st_body)
    return out


def render_posegraph(doc):
    rows = doc.get("rows", [])
    if doc.get("suite") == "thesis":
        out = [
            "Thesis chapter 7 comparison (tables 7.1-7.4 analogues). RMSE: positions against the "
            "ground truth after rigid alignment; 'vs SE': against this run's SE(n) solution from "
            "the linear / chordal initialisation.",
            "",
        ]
        body = [[f"`{r['file']}`", r["method"], r.get("variables", "-"), r.get("iterations", "-"),
                 num(r.get("s"), ".3f"), num(r.get("chi2"), ".5g"), num(r.get("rmse_gt_m"), ".4f"),
                 num(r.get("rmse_vs_se_m"), ".4f")] for r in rows]
        return out + table(["file", "method", "variables", "iterations", "s", "chi2", "RMSE m", "vs SE m"], body)
    solver = doc.get("solver", {})
    measured = all(r.get("gtsam_measured") for r in rows if r.get("gtsam"))
    out = [
        "rgbid: median of {} solves with `--param {} --cost {} --init {}` (initialisation "
        "included). GTSAM: its run with the lowest chi2 among LM, GN and (3D) chordal + LM, {}. "
        "F is the SE-Sync objective, f* its certified global optimum.".format(
            doc.get("repeat", "?"), solver.get("param", "?").lower(), solver.get("cost", "?").lower(),
            solver.get("init", "?").lower(),
            "measured in the same run" if measured else "figures from the data README (not measured in this run)",
        ),
        "",
    ]
    body = []
    worse = False
    for r in rows:
        g = r.get("gtsam") or {}
        fstar = r.get("fstar")
        mark = ""
        if g.get("chi2") is not None and r.get("chi2") is not None and g["chi2"] > 1.01 * r["chi2"]:
            mark, worse = " *", True
        body.append([
            f"`{r['file']}`", r.get("poses", "-"), r.get("edges", "-"),
            num(r.get("chi2"), ".5g"), num(g.get("chi2"), ".5g") + mark,
            num(r["F"] / fstar if fstar else None, ".4f"),
            r.get("iterations", "-"), num(r.get("s"), ".3f"),
            f"{num(g.get('s'), '.3f')} ({g['method']})" if g else "-",
            num(r.get("speedup_vs_gtsam"), ".2f") + "x" if r.get("speedup_vs_gtsam") else "-",
        ])
    out += table(["file", "poses", "edges", "rgbid chi2", "GTSAM chi2", "rgbid F/f*", "rgbid iterations",
                  "rgbid s", "GTSAM s (run)", "speed-up vs GTSAM"], body)
    if worse:
        out += ["", "\\* GTSAM ended more than 1 % above rgbid's chi2 (a local minimum reached from the "
                "file's initial values), so its time is for a worse result."]
    return out


def render_kernels(doc):
    out = [f"Generated frames, median of {doc.get('repeat', '?')} repetitions; align = pyramids of both "
           "frames + coarse-to-fine Gauss-Newton.", ""]
    body = [[r["backend"], f"{r['width']}x{r['height']}", num(r["align_ms"], ".2f"), num(r["pyramid_ms"], ".2f"),
             num(r["scale_ms"], ".2f"), num(r["reduce_ms"], ".2f"), num(r["solve_ms"], ".3f"), r["iterations"]]
            for r in doc.get("rows", [])]
    out += table(["backend", "size", "align ms", "pyramid ms", "scale ms", "reduce ms", "solve ms", "GN iterations"], body)
    frames = doc.get("frame_rows", [])
    if frames:
        out += ["", "Keyframe fusion of one frame into a resident keyframe, and ray casting of one frame "
                "of the generated office scene (no sensor model):", ""]
        out += table(["backend", "size", "fuse ms", "ray cast ms"],
                     [[r["backend"], f"{r['width']}x{r['height']}", num(r["fuse_ms"], ".2f"),
                       num(r["raycast_ms"], ".2f")] for r in frames])
    und = doc.get("undistort_rows", [])
    if und:
        out += ["", "Undistortion of one frame (TUM fr1 distortion, CPU remap as in the I/O thread):", ""]
        out += table(["backend", "size", "undistort ms"],
                     [[r["backend"], f"{r['width']}x{r['height']}", num(r["undistort_ms"], ".2f")] for r in und])
    return out


def render_gpu_check(doc):
    out = [f"`scripts/gpu-check.sh` (bundle from `scripts/gpu-bundle.sh`), {doc.get('check_seconds', '?')} s in all.",
           "", "GPU tests (`gpu_*`, `RGBID_REQUIRE_GPU=1`):", ""]
    out += table(["test executable", "exit", "passed", "failed", "seconds"],
                 [[t.get("executable"), t.get("exit"), t.get("passed"), t.get("failed"), t.get("seconds")]
                  for t in doc.get("tests", [])])
    out += ["", "Odometry kernels, keyframe fusion and ray casting per backend:", ""]
    out += render_kernels(doc)
    if "tsdf" in doc:
        out += ["", "TSDF integration and ray casting (`rgbid bench tsdf`, no peer):", ""]
        out += render_generic(doc["tsdf"])
    return out


def render_python_overhead(doc):
    out = [f"`python/benchmarks/overhead.py`: {doc.get('sequence', '?')}, frames rendered before timing, "
           f"the first {doc.get('warmup', '?')} left out. Per frame, the wall time of the Python call "
           "(`Odometry.track`, `Slam.process`) against `rust_ms`, the time the binding measured inside "
           "the library for the same call (`RgbdFrame::from_buffers` + track / process). Medians over "
           "the frames; goal: overhead under 5 %.", ""]
    body = [[r["system"], r["backend"], f"{r['width']}x{r['height']}", r["frames"], num(r["python_ms"], ".3f"),
             num(r["rust_ms"], ".3f"), num(r["overhead_ms"], ".4f"), num(r["overhead_pct"], ".2f") + " %"]
            for r in doc.get("rows", [])]
    out += table(["system", "backend", "size", "frames", "Python ms", "Rust ms", "overhead ms", "overhead"], body)
    return out


def slope(points):
    """Least-squares slope of y over x of (x, y) points; None with fewer than two distinct x."""
    if len(points) < 2:
        return None
    mx = sum(p[0] for p in points) / len(points)
    my = sum(p[1] for p in points) / len(points)
    sxx = sum((p[0] - mx) ** 2 for p in points)
    if sxx == 0:
        return None
    return sum((p[0] - mx) * (p[1] - my) for p in points) / sxx


def render_load(doc):
    mb = lambda b: num(None if b is None else b / 1e6, ".1f")
    out = [f"`rgbid bench load`: {doc.get('frames', '?')} generated frames ({doc.get('width', '?')}x"
           f"{doc.get('height', '?')}, `office:loop`, a lap every 300 frames, CPU backend) in "
           f"{num(doc.get('wall_s'), '.0f')} s, {doc.get('keyframes', '?')} keyframes. Memory sampled "
           "during the run: the process (VmRSS), its live heap (allocated and not freed, counted by the "
           "program's allocator) and the SLAM instance's own account." + (
               "" if doc.get("complete", True) else
               f" Partial report, written after frame {(doc.get('samples') or [{}])[-1].get('frame', '?')} (the run had not finished)"
               " (the figures below are of the samples so far)."), ""]
    has_heap = any("heap_bytes" in s for s in doc.get("samples", []))
    if has_heap:
        out += table(["frame", "keyframes", "process MB", "heap MB", "instance MB"],
                     [[s["frame"], s["keyframes"], mb(s.get("rss_bytes")), mb(s.get("heap_bytes")),
                       mb(s.get("instance_bytes"))] for s in doc.get("samples", [])])
    else:
        out += table(["frame", "keyframes", "process MB", "instance MB"],
                     [[s["frame"], s["keyframes"], mb(s.get("rss_bytes")), mb(s.get("instance_bytes"))]
                      for s in doc.get("samples", [])])
    heap = (f"heap {num(doc.get('heap_bytes_per_keyframe'), '.0f')}, " if has_heap else "")
    out += ["", "Bytes per keyframe (slope over the keyframe count): process "
            f"{num(doc.get('rss_bytes_per_keyframe'), '.0f')}, {heap}instance "
            f"{num(doc.get('instance_bytes_per_keyframe'), '.0f')}, saved map "
            f"{num(doc.get('map_bytes_per_keyframe'), '.0f')}. Process memory besides the instance "
            f"grows {num(doc.get('other_bytes_per_frame'), '.1f')} bytes per frame (slope over frames)."]
    if has_heap:
        half = [x for x in doc.get("samples", []) if 2 * x["frame"] >= doc.get("frames", 0)]
        out += ["Over the second half of the run (least-squares slope over frames): live heap outside "
                "the instance's account grows "
                f"{num(slope([(x['frame'], x['heap_bytes'] - x['instance_bytes']) for x in half]), '.1f')} "
                "bytes per frame, the process beyond its live heap "
                f"{num(slope([(x['frame'], x['rss_bytes'] - x['heap_bytes']) for x in half if x.get('rss_bytes')]), '.1f')} "
                "bytes per frame. The heap outside the account is one block per thread that factorises "
                "the keyframe pose graph (the back-end and the rayon workers): the GEMM kernel under faer's supernodal Cholesky "
                "(`private-gemm-x86`) reserves a thread-local scratch of twice the L3 cache on its first "
                "call, once the graph is large enough for supernodes (`RGBID_HEAP_TRACE_ABOVE` shows "
                "where); its pages become resident as the supernodes grow, so the process stays below its "
                "live heap until that reservation is touched. What grows per frame beyond it is given "
                "above: live heap the account misses, and pages the C allocator keeps after frees."]
    out += [""]
    t = doc.get("threads")
    if t:
        out += [f"Two sessions of {t['frames']} frames in one process: one after the other "
                f"{num(t['sequential_s'], '.1f')} s, on two threads {num(t['parallel_s'], '.1f')} s; poses "
                f"{t['poses'][0]} and {t['poses'][1]}; largest difference of a pose between the two "
                f"ways {num(t['max_difference_m'], '.3g')} m."]
    return out


def render_scale_sweep(doc):
    out = [f"`rgbid scale experiment --sweep`: the thesis' table 3.1 on generated walks "
           f"({', '.join(doc.get('sequences', []))}; {num(doc.get('duration_s'), '.0f')} s each, "
           f"{doc.get('seeds', '?')} seeds, {doc.get('estimator', '?')} monocular estimates, "
           f"{doc.get('particles', '?')} particles). dynScale's arc-length error (eq. 3.36, rigid "
           "alignment, % of the path: mean and worst run), the median per-section scale error "
           "|s / s_true - 1| and the share of sections detected as walking, per analysis window "
           "t_DFT and update period t_upd.", ""]
    body = [[num(r["t_dft"], ".1f"), num(r["t_upd"], ".1f"), r["runs"], num(r["rel_error_pct"], ".2f"),
             num(r["rel_error_max_pct"], ".2f"), num(r["scale_error_median_pct"], ".2f"),
             num(r["walking_pct"], ".1f")] for r in doc.get("rows", [])]
    out += table(["t_DFT (s)", "t_upd (s)", "runs", "error (%)", "worst (%)", "scale error (%)",
                  "walking (%)"], body)
    return out


def render_mono_walks(doc):
    """Metric monocular SLAM on generated walks: eq. 3.36 of each trajectory, start-aligned."""
    rows = doc.get("rows", [])
    with_loops = any("loops" in r for r in rows)
    out = ["`rgbid mono --synthetic omni --walker-height 1.75" + (" --loops" if with_loops else "")
           + "` on generated catadioptric walks "
           "(400x400, 30 Hz; the default pace schedule with stops): the EKF, and the scale "
           "estimation of Algorithm 1 beside it, frame by frame. Errors are eq. 3.36 as the thesis "
           "scores walks: the trajectory is placed on the ground truth at its first pose and never "
           "rescaled, then compared by normalised arc length (mean and end error, % of the path "
           "walked). *causal*: each frame's metric pose as it was output (from the first frame "
           "with a scale on, so over a shorter path); *final*: each section scaled with the scale "
           "at its end (dynScale alone). *final, rigidly aligned*: the final output's position "
           "RMSE after the rigid motion that fits it best (no rescaling, % of the path): its metric "
           "shape and scale without the attitude error that the placement at the first pose "
           "carries along the walk. The last column is the EKF's own shape error "
           "(Sim(3)-aligned ATE, % of the path).", ""]
    def pair(r, key):
        e = r.get(key) or {}
        return [num(e.get("mean_pct"), ".2f"), num(e.get("end_pct"), ".2f"), num(e.get("length_ratio"), ".3f")]
    body = []
    for r in rows:
        if r.get("missing"):
            body.append([r["sequence"], "(failed)"] + ["-"] * 15)
            continue
        body.append([r["sequence"], num(r.get("path_m") or (r.get("final") or r.get("unscaled") or {}).get("path_m"), ".1f"),
                     f"{r.get('walking_sections', 0)}/{r.get('sections', 0)}"]
                    + pair(r, "unscaled") + pair(r, "causal") + pair(r, "final")
                    + [num((r.get("final") or {}).get("rigid_ate_pct"), ".2f"),
                       num(r.get("filter_ms"), ".2f"), num(r.get("scale_ms"), ".4f"),
                       num(r.get("ekf_sim3_ate_pct"), ".2f")])
    out += table(["walk", "path m", "walking", "unscaled mean %", "end %", "length", "causal mean %",
                  "end %", "length", "final mean %", "end %", "length",
                  "final, rigidly aligned %", "filter ms/frame",
                  "scale ms/frame", "EKF Sim(3) ATE %"], body)
    own = [(r["sequence"], r["meta"]) for r in rows if isinstance(r.get("meta"), dict)]
    if own:
        out += ["", "Run apart from the others: " + "; ".join(
            f"{name} measured {str(m.get('date_utc', '?'))[:10]} at commit `{m.get('commit', '?')}`"
            + (" (with uncommitted changes)" if m.get("dirty") else "") for name, m in own) + "."]
    if not with_loops:
        return out
    out += ["", "With loops from the images (thesis 3.3.2): keyframes from the EKF stream, ORB + bag "
            "of words, essential-matrix verification; each loop's similarity from the two keyframes' "
            "own triangulations against their neighbouring keyframes (the scale ratio of eq. 3.10), "
            "carried into metres by each keyframe's section scale; optimSim3 over the keyframes with "
            "the walking scale of each section as a prior. *true*: loops that are true by the ground "
            "truth (positions within 1.5 m, optical axes within 90 degrees; scoring only). *t err*: "
            "median error of the used loops' metric translation against the true relative "
            "translation. The same eq. 3.36 errors: unscaled, dynScale alone, dynScale + image loops; "
            "*online*: each frame's causal metric pose corrected by the loops found up to it "
            "(optimSim3 on the run so far at each loop; over the causal poses' shorter path, so "
            "compare it with the causal column above). *at equal times*: the same start placement, "
            "the mean distance to the ground truth at the same time stamps (% of the path), which "
            "does not depend on how the trajectory spends its arc length: a correction's jump "
            "lengthens the path, and eq. 3.36's matching by normalised arc length counts that.",
            ""]
    body = []
    for r in rows:
        if r.get("missing"):
            continue
        def mean(key):
            return num((r.get(key) or {}).get("mean_pct"), ".2f")
        def end(key):
            return num((r.get(key) or {}).get("end_pct"), ".2f")
        body.append([r["sequence"], r.get("keyframes", "-"),
                     f"{r.get('loops_true', '-')}/{r.get('loops_verified', '-')}", r.get("loops_used", "-"),
                     num(r.get("loop_translation_error_m"), ".3f"),
                     mean("unscaled"), mean("final"), mean("loops"), end("final"), end("loops"),
                     num((r.get("loops") or {}).get("length_ratio"), ".3f"),
                     mean("causal_loops"), end("causal_loops"),
                     num((r.get("causal") or {}).get("time_matched_pct"), ".2f"),
                     num((r.get("causal_loops") or {}).get("time_matched_pct"), ".2f")])
    out += table(["walk", "keyframes", "loops true/verified", "used", "t err m", "unscaled mean %",
                  "dynScale mean %", "dynScale + loops mean %", "dynScale end %",
                  "dynScale + loops end %", "length (loops)", "online mean %", "online end %",
                  "causal at equal times %", "online at equal times %"], body)
    return out
def render_mono_patch_modes(doc):
    """The monocular EKF per patch mode on generated walks."""
    out = ["`rgbid mono --synthetic omni --walker-height 1.75 --patch MODE` on the generated 60 s "
           "head-worn catadioptric walks (400x400, 30 Hz, seed 7), one run per patch mode. *EKF "
           "Sim(3) ATE*: the filter's own trajectory after a similarity alignment, % of the path "
           "(the drift the scale chain cannot remove); then eq. 3.36 (start-aligned, not rescaled, "
           "mean and end error in % of the path) of the unscaled EKF trajectory, of each frame's "
           "causal metric pose and of the final dynScale output (*-*: no walking detected, so no metric "
           "output). Modes: see `mono::PatchMode`. The runs shared a loaded machine, so the ms per "
           "frame are not comparable between rows.", ""]
    body = []
    for r in doc.get("rows", []):
        if r.get("missing"):
            body.append([r.get("mode", "?"), r.get("sequence", "?"), "(failed)"] + ["-"] * 8)
            continue
        def pair(key):
            e = r.get(key) or {}
            return [num(e.get("mean_pct"), ".2f"), num(e.get("end_pct"), ".2f")]
        body.append([r.get("mode", "?"), r.get("sequence", "?"), num(r.get("ekf_sim3_ate_pct"), ".2f"),
                     num(r.get("ekf_sim3_scale"), ".3f")]
                    + pair("unscaled") + pair("causal") + pair("final") + [num(r.get("filter_ms"), ".2f")])
    out += table(["patch", "walk", "EKF Sim(3) ATE %", "Sim(3) scale", "unscaled mean %", "end %",
                  "causal mean %", "end %", "final mean %", "end %", "filter ms/frame"], body)
    return out


def render_patch_sweeps(doc):
    """The decoupled matching experiment (thesis 2.6.1): one row per sweep step, one column per patch mode."""
    spec = doc.get("spec", {})
    rows = doc.get("rows", [])
    modes = []
    for r in rows:
        if r["mode"] not in modes:
            modes.append(r["mode"])
    out = [f"`rgbid mono --patch-sweeps`: {doc.get('reference_features', '?')} FAST features of a "
           f"generated {spec.get('width', '?')}x{spec.get('height', '?')} catadioptric image "
           f"({spec.get('scene', '?')}, seed {spec.get('seed', '?')}, the head-worn walk's pose at "
           f"{num(spec.get('reference_time'), '.1f')} s: optical axis near horizontal) searched by ZNCC in a "
           f"{2 * spec.get('search_half', 0) + 1} px window around their true projection after a turn "
           "about the vertical (degrees), a step along the floor in the heading (metres) and, per "
           "feature, a move along its ray to distance d_init / factor (scale). The warps get the true "
           "relative pose and distance (a converged depth). Each cell: % of the visible features whose "
           "best position is within 2 px of the truth / % also scoring ZNCC >= "
           f"{num(spec.get('zncc_threshold'), '.2f')} (what the filter accepts). *n*: features visible "
           "and not occluded.", ""]
    steps = []
    for r in rows:
        key = (r["sweep"], r["step"])
        if key not in steps:
            steps.append(key)
    body = []
    for sweep, step in steps:
        cells = {r["mode"]: r for r in rows if r["sweep"] == sweep and r["step"] == step}
        n = next(iter(cells.values()))["features"]
        unit = {"rotation": " deg", "translation": " m", "scale": "x"}.get(sweep, "")
        body.append([sweep, num(step, "g") + unit, n]
                    + [f"{num(cells[m]['within_2px_pct'], '.0f')} / {num(cells[m]['matched_pct'], '.0f')}"
                       if m in cells else "-" for m in modes])
    out += table(["sweep", "step", "n"] + modes, body)
    return out


def render_mono_loops(doc):
    """Monocular loop detection from images on generated walks: precision / recall and a sweep."""
    rows = [r for r in doc.get("rows", []) if not r.get("missing")]
    first = (rows[0].get("evaluation", {}) if rows else {})
    p, t = first.get("params", {}), first.get("truth", {})
    out = ["`rgbid mono --synthetic omni --loops` on generated catadioptric walks (30 Hz, the default "
           "pace schedule with stops): keyframes from the EKF stream, ORB + bag of words inside the "
           f"mirror, candidates at least {p.get('min_time_separation', '?')} s older than the query "
           f"(best {p.get('max_candidates', '?')} verified), essential-matrix RANSAC on the bearings "
           f"({p.get('angular_threshold', '?')} rad). A true loop: true camera positions within "
           f"{t.get('max_distance', '?')} m and optical axes within {t.get('max_axis_angle_deg', '?')} "
           "degrees (ground truth only scores). Precision: true / accepted loops (at most one per "
           "query keyframe); recall: query keyframes with a true accepted loop / query keyframes that "
           "have a true partner outside the temporal window. Defaults: normalised score >= "
           f"{p.get('min_normalised_score', '?')}, inliers >= {p.get('min_inliers', '?')}, inlier ratio "
           f">= {p.get('min_inlier_ratio', '?')}.", ""]
    body = []
    for r in doc.get("rows", []):
        if r.get("missing"):
            body.append([r["sequence"], "(failed)"] + ["-"] * 8)
            continue
        e = r.get("evaluation", {})
        sc = e.get("score", {})
        body.append([r.get("sequence", "?"), f"{r.get('width', '?')}x{r.get('height', '?')}",
                     num(e.get("path_length"), ".1f"), len(e.get("keyframe_frames", [])),
                     sc.get("loop_queries", "-"), f"{sc.get('true_positives', '-')}/{sc.get('detected', '-')}",
                     num(sc.get("precision"), ".3f"), num(sc.get("recall"), ".3f"),
                     num(e.get("keyframe_ms"), ".1f"), num(e.get("ate_rmse"), ".3f")])
    out += table(["walk", "image", "path m", "keyframes", "with a true partner", "true/loops",
                  "precision", "recall", "loop ms/keyframe", "EKF Sim(3) ATE m"], body)
    for r in rows:
        e = r.get("evaluation", {})
        sc = e.get("score", {})
        sweep = e.get("sweep", [])
        scores = sorted({w["min_normalised_score"] for w in sweep})
        inl = sorted({w["min_inliers"] for w in sweep})
        ratios = sorted({w["min_inlier_ratio"] for w in sweep})
        cell = {(w["min_normalised_score"], w["min_inliers"], w["min_inlier_ratio"]): w for w in sweep}
        key = lambda w: (w["detected"], w["true_positives"])
        shown = [q for q in ratios if q == sc.get("min_inlier_ratio")] or ratios[-1:]
        same = all(key(cell[(a, n, q)]) == key(cell[(a, n, shown[0])])
                   for a in scores for n in inl for q in ratios if (a, n, q) in cell and shown)
        note = ("the same at every inlier ratio swept (" + ", ".join(f"{q:g}" for q in ratios) + ")"
                if same else "other inlier ratios in the JSON")
        out += ["", f"Sweep on {r.get('sequence', '?')}: precision / recall (loops accepted) by "
                f"normalised score (rows) and inliers (columns), inlier ratio >= {shown[0] if shown else '?'}; "
                f"{note}. {e.get('false_candidates', '?')} checked candidates were not true loops; the most "
                f"inliers among them: {e.get('false_candidate_max_inliers', '?')}"
                + (" (true positions {:.2} m apart, optical axes {:.0} degrees)".format(*e["false_candidate_max_truth"])
                   if e.get("false_candidate_max_truth") else "") + ".", ""]
        sbody = []
        for a in scores:
            line = [f"{a:.2f}"]
            for n in inl:
                w = cell.get((a, n, shown[0])) if shown else None
                line.append("-" if w is None else
                            f"{w['precision']:.3f} / {w['recall']:.3f} ({w['detected']})")
            sbody.append(line)
        out += table(["score \\ inliers"] + [str(n) for n in inl], sbody)
        false = [l for l in e.get("loops", []) if not l.get("correct")]
        if false:
            out += ["", "False loops at the defaults (frames, true distance m, axis angle deg, inliers): "
                    + "; ".join(f"{l['query_frame']}->{l['candidate_frame']} ({l['true_distance_m']:.2f}, "
                                f"{l['true_axis_angle_deg']:.0f}, {l['inliers']})" for l in false)]
    return out
def render_layouts(doc):
    out = [f"`rgbid slam DIR` on one generated sequence ({doc.get('scene', '?')} "
           f"{doc.get('trajectory', '?')}, {doc.get('frames', '?')} frames at {doc.get('width', '?')}x"
           f"{doc.get('height', '?')}, Kinect-like noise, seed {doc.get('seed', '?')}, "
           f"{doc.get('backend', '?')} backend) written by `rgbid synth --layout` in each dataset layout, "
           "the layout detected from the folder (no `--format`); ATE RMSE of the SLAM trajectory against "
           "the ground truth that layout carries (`summary.json`). The folders hold the same frames: "
           "differences come from depth quantisation (TUM, ETH3D 0.2 mm; 7-Scenes, ScanNet 1 mm; "
           "Replica 0.15 mm) and colour coding (ScanNet, Replica JPEG; ScanNet colour upsampled 2x "
           "and resampled onto the depth camera). fps: frames / wall time of the whole run "
           "(loading, back-end and output included).", ""]
    body = [[r["layout"], "yes" if r.get("detected") else "no", r["frames"], r["keyframes"],
             num(r.get("ate_m"), ".4f"), num(r.get("odometry_ate_m"), ".4f"), num(r.get("fps"), ".1f")]
            for r in doc.get("rows", [])]
    return out + table(["layout", "detected", "frames", "keyframes", "ATE m", "odometry ATE m", "fps"], body)


def render_camera_rate(doc):
    """Camera rate on real data: whole-process wall time against camera time."""
    out = [f"`rgbid slam SEQ --backend cpu --out DIR` and `rgbid odometry SEQ --backend cpu`, "
           f"{doc.get('runs', '?')} runs each (medians): wall time of the whole process (start-up, "
           "loading and decoding, back-end, final optimisation and output files) against the "
           "sequence's camera time (first to last time stamp plus one 30 Hz period); front-end "
           "milliseconds per frame from `timing.csv` (percentiles over the frames, median over the "
           "runs); odometry wall time per frame with decoding, against OpenCV RGB_DEPTH's per-frame "
           "compute median (`peer_odometry.py --methods cv_rgbd`, same script run). The 1-minute "
           "load average before each run is in the report (`load_1min`). *Cores delivered*: two "
           "single-threaded loops timed together against one alone, before the sequence's runs "
           "(2.00 on two free cores; less where the host shares them, which a load average does "
           "not show).", ""]
    body = []
    for r in doc.get("rows", []):
        loads = r.get("load_1min") or []
        body.append([r["sequence"], r["frames"], num(r.get("camera_s"), ".2f"),
                     num(r.get("slam_wall_s_median"), ".2f"),
                     num(r["camera_s"] / r["slam_wall_s_median"], ".2f") if r.get("slam_wall_s_median") else "-",
                     num(r.get("frontend_ms_p50"), ".1f"), num(r.get("frontend_ms_p95"), ".1f"),
                     num(r.get("frontend_ms_max"), ".1f"), num(r.get("slam_ate_m"), ".4f"),
                     num(r.get("odometry_wall_ms_per_frame"), ".1f"), num(r.get("opencv_ms_per_frame"), ".1f"),
                     num(r.get("opencv_over_rgbid"), ".2f"),
                     num(max(loads), ".2f") if loads else "-", " / ".join(num(c, ".2f") for c in r.get("cores_delivered") or []) or "-"])
    return out + table(["sequence", "frames", "camera s", "slam wall s", "camera / wall",
                        "front-end ms p50", "p95", "max", "SLAM ATE m", "odometry ms/frame (wall)",
                        "OpenCV ms/frame (compute)", "OpenCV / rgbid", "highest load",
                        "cores delivered before / after"], body)


def render_generic(doc):
    rows = [r for r in doc.get("rows", []) if isinstance(r, dict)]
    keys = []
    for r in rows:
        keys += [k for k, v in r.items() if k not in keys and (v is None or isinstance(v, (str, int, float, bool)))]
    body = [[num(r.get(k), ".4g") if isinstance(r.get(k), float) else ("-" if r.get(k) is None else r.get(k))
             for k in keys] for r in rows]
    return table(keys, body) if keys else ["(no rows)"]


def render_thesis_tables(doc):
    """Tables 4.1-4.3 and 6.1 of the thesis, one table each, both sequences side by side."""
    heads = {
        "peer": "OpenCV RGB_DEPTH (the peer of every ratio below, same script run)",
        "4.1": "Table 4.1: robust estimator x geometric parametrisation x scale estimate",
        "4.2": "Table 4.2: residual terms",
        "4.3": "Table 4.3: performance options",
        "6.1": "Table 6.1: odometry, SLAM without and with loop closure",
    }
    rows = doc.get("rows", [])
    out = [f"Load average at start / end: {doc.get('meta', {}).get('load', '?')}. The accuracy "
           "columns do not depend on the load; ms/frame (median compute per frame) does, and each "
           "variant ran at a different moment, so compare times only from a run on an idle machine."]
    if doc.get("missing"):
        out.append("Runs missing (failed or not run): " + ", ".join(doc["missing"]))
    for key, head in heads.items():
        sel = [r for r in rows if r.get("table") == key]
        if not sel:
            continue
        out += ["", f"**{head}**", ""]
        body = [[r["sequence"], r["variant"], num(r.get("ate_m"), ".4f"), num(r.get("ate_over_opencv"), ".3f"),
                 num(r.get("rpe_m_per_s"), ".4f"), num(r.get("rpe_deg_per_s"), ".3f"),
                 num(r.get("ms_median"), ".1f")]
                for r in sel]
        out += table(["sequence", "variant", "ATE m", "ATE / OpenCV", "RPE m/s", "RPE deg/s",
                      "ms/frame"], body)
        walls = [f"{r['sequence']} {num(r['slam_wall_s'], '.1f')} s" for r in sel if r.get("slam_wall_s") is not None]
        if key == "6.1" and walls:
            out += ["", "`rgbid slam` wall time (loading and output included, under the load above): "
                    + "; ".join(dict.fromkeys(walls)) + "."]
    return out


def render_mesh_change(doc):
    c = doc.get("config", {})
    tsdf = c.get("tsdf", {})
    g = doc.get("ground_truth", {})
    out = [f"`rgbid segment mesh-experiment`: the thesis' mesh experiment (eq. 5.3, figs. 5.9-5.10) "
           f"on generated loops ({', '.join(c.get('scenes', []))}; seeds {c.get('seeds', '?')}; "
           f"{c.get('sessions', '?')} changed sessions each; {c.get('lap_frames', '?')} frames per "
           f"session at {c.get('width', '?')} px, sensor `{doc.get('sensor', '?')}`, TSDF voxels "
           f"{num(tsdf.get('voxel_size'), '.3f')} m, mesh segments of >= "
           f"{c.get('segment', {}).get('min_size', '?')} vertices). A changed-session vertex is "
           f"changed (eq. 5.3) when no session-0 surface lies within "
           f"{num(c.get('change_distance'), '.2f')} m; areas are area-weighted over vertices.", "",
           "Eq. 5.3 against the generator's labels (vertex on a moved or added object): "
           f"{num(g.get('eq53_changed_m2'), '.1f')} m^2 changed of {num(g.get('area_m2'), '.1f')} m^2, "
           f"{num(g.get('generator_changed_m2'), '.1f')} m^2 on moved/added objects; agreement "
           f"{num(g.get('agreement'), '.3f')}, precision {num(g.get('eq53_precision'), '.3f')}, "
           f"recall {num(g.get('eq53_recall'), '.3f')}; {num(g.get('off_surface_m2'), '.1f')} m^2 of "
           "mesh off every true surface of its session (artefacts) left out.", "",
           "Changed-area detection (segments with neg-entropy below the threshold masked):", ""]
    body = [["< " + num(d["threshold"], ".2f"), num(d["masked_share"], ".3f"), num(d["precision"], ".3f"),
             num(d["recall"], ".3f"), num(d["recall_generator"], ".3f"), num(d["static_kept"], ".3f")]
            for d in doc.get("detection", [])]
    out += table(["mask", "masked area", "precision", "recall (eq. 5.3)", "recall (generator)",
                  "unchanged area kept"], body)

    def matching(rows):
        return table(["mask", "kept keypoints", "matches", "on changed objects", "inlier ratio",
                      "precision", "recall"],
                     [["none" if r["threshold"] is None else ">= " + num(r["threshold"], ".2f"),
                       num(r["kept_keypoints"], ".2f"), r["matches"], r["matches_on_changed"],
                       num(r["inlier_ratio"], ".3f"), num(r["precision"], ".3f"), num(r["recall"], ".3f")]
                      for r in rows])
    out += ["", f"Matching session 0 against the changed sessions with the projected mesh masks "
            f"({doc.get('pairs', '?')} pairs, {doc.get('pairs_with_changes', '?')} see changed objects):", ""]
    out += matching(doc.get("matching", []))
    for v in doc.get("cluttered_views", []):
        if v.get("pairs"):
            out += ["", f"Views of moved clutter ({v['pairs']} pairs whose unmasked matches lie on changed "
                    f"objects for >= {num(100 * v['min_changed_share'], '.0f')} %):", ""]
            out += matching(v["matching"])
    out += ["", "Median per session: render + integrate {} s, mesh {} s, segmentation {} s, ground truth "
            "{} s; {} s in all.".format(num(doc.get("integrate_s"), ".1f"), num(doc.get("extract_s"), ".1f"),
                                        num(doc.get("segment_s"), ".1f"), num(doc.get("ground_truth_s"), ".1f"),
                                        num(doc.get("wall_s"), ".0f"))]
    return out


def render_rolling_shutter(doc):
    """The readout sweep of the Kinect v1 presets: per sequence, then the mean ratio."""
    rows = doc.get("rows", [])
    peers = doc.get("opencv", {})
    out = ["`rgbid odometry` and `rgbid slam` (CPU, default configuration) on the two real "
           "sequences with the sequence's camera plus a rolling-shutter readout (seconds from the "
           "first row to the last; 0 is a global shutter: no rectification). ATE and RPE by "
           "`rgbid eval`; OpenCV RGB_DEPTH (`peer_odometry.py --methods cv_rgbd`) ran in the same "
           "script run and is scored by the same evaluator: "
           + "; ".join(f"{k} ATE {num(v.get('ate_m'), '.4f')} m, RPE {num(v.get('rpe_m_per_s'), '.4f')} m/s"
                       for k, v in peers.items()) + ".", ""]
    body = [[r["sequence"], num(r["readout_s"] * 1e3, ".1f"), num(r.get("ate_m"), ".4f"),
             num(r.get("ate_over_opencv"), ".3f"), num(r.get("rpe_m_per_s"), ".4f"),
             num(r.get("slam_ate_m"), ".4f"), r.get("slam_keyframes", "-"), r.get("slam_loops", "-")]
            for r in rows]
    out += table(["sequence", "readout ms", "odometry ATE m", "ATE / OpenCV", "odometry RPE m/s",
                  "SLAM ATE m", "keyframes", "loops"], body)
    by = {}
    for r in rows:
        by.setdefault(r["readout_s"], []).append(r.get("ate_over_opencv"))
    means = {k: sum(v) / len(v) for k, v in by.items() if len(v) == len(peers) and None not in v}
    if means:
        best = min(means, key=means.get)
        out += ["", "Mean of odometry ATE / OpenCV's ATE over the sequences (the rule for the "
                "odometry's defaults; lowest in bold):", ""]
        out += table(["readout ms", "mean ATE / OpenCV"],
                     [[("**{}**" if k == best else "{}").format(num(k * 1e3, ".1f")),
                       ("**{}**" if k == best else "{}").format(num(v, ".3f"))]
                      for k, v in sorted(means.items())])
    return out


RENDERERS = {"odometry": render_odometry, "posegraph": render_posegraph, "kernels": render_kernels,
             "gpu-check": render_gpu_check, "python-overhead": render_python_overhead,
             "load": render_load, "thesis-tables": render_thesis_tables,
             "scale-sweep": render_scale_sweep, "mono-walks": render_mono_walks, "mono-loops": render_mono_loops,
             "patch-sweeps": render_patch_sweeps, "mono-patch-modes": render_mono_patch_modes,
             "layouts": render_layouts, "camera-rate": render_camera_rate,
             "rolling-shutter": render_rolling_shutter,
             "mesh-change": render_mesh_change}
TITLES = {"odometry": "Odometry", "posegraph": "Pose graphs", "kernels": "Odometry kernels",
          "tsdf": "TSDF reconstruction (`rgbid bench tsdf`)",
          "gpu-check": "GPU check on a real GPU", "python-overhead": "Python per-frame overhead",
          "thesis-options": "Thesis formulations as options on real data",
          "thesis-tables": "Thesis tables 4.1-4.3 and 6.1 on real data",
          "load": "SLAM under load", "scale-sweep": "Walking scale: t_DFT / t_upd (table 3.1)",
          "mono-walks": "Metric monocular SLAM on generated walks",
          "mono-loops": "Monocular loop detection from images",
          "mono-patch-modes": "Monocular EKF per patch mode on generated walks",
          "patch-sweeps": "Catadioptric patch warping: decoupled matching (thesis 2.6.1)",
          "layouts": "`rgbid slam` on every dataset layout",
          "camera-rate": "Camera rate on real data (`scripts/camera_rate.py`)",
          "rolling-shutter": "Rolling-shutter readout of the Kinect presets (`scripts/rolling_shutter.py`)",
          "mesh-change": "Changed scenes on TSDF meshes (thesis eq. 5.3, figs. 5.9-5.10)"}


def title(doc):
    kind = doc.get("benchmark", "?")
    t = TITLES.get(kind, kind)
    if kind == "odometry":
        t += f" on `{doc.get('sequence_name', '?')}`"
    if kind == "mesh-change":
        t += f", sensor `{doc.get('sensor', '?')}`"
    if kind == "posegraph":
        t += f" (`--suite {doc.get('suite', 'files')}`)"
    return t


def render(root):
    reports = sorted((root / "docs" / "results").glob("*.json"))
    out = [
        "# Results",
        "",
        f"<!-- Generated by `{COMMAND}` from docs/results/*.json. Do not edit by hand: rerun the "
        "benchmark with `--json docs/results/NAME.json`, then the script. -->",
        "",
        f"Generated by `{COMMAND}` from the benchmark reports in `docs/results/` (each written by "
        "a benchmark's `--json FILE`). Every section names its command, date, commit and machine. "
        "Ratios against peers are measured in the same run and are the figures to compare; "
        "absolute times move with the machine and its load. `" + COMMAND + " --check` fails "
        "when this file is out of date.",
        "",
    ]
    docs = []
    for p in reports:
        with open(p, encoding="utf-8") as f:
            docs.append((p.name, json.load(f)))
    # Known benchmarks first (odometry, pose graphs, kernels), then any other, by file name.
    order = {kind: i for i, kind in enumerate(RENDERERS)}
    docs.sort(key=lambda nd: (order.get(nd[1].get("benchmark"), len(order)), nd[0]))
    if not docs:
        out.append("(no reports yet)")
    else:
        out += [f"- [{title(d)}](#{anchor(title(d))}) (`{n}`)" for n, d in docs]
    for name, doc in docs:
        out += ["", f"## {title(doc)}", ""]
        out += provenance(doc, name)
        out.append("")
        out += RENDERERS.get(doc.get("benchmark"), render_generic)(doc)
    return "\n".join(out) + "\n"


HEADLINE_REPORT = "odometry_redkitchen.json"
HEADLINE_BEGIN = "<!-- headline:begin -->"
HEADLINE_END = "<!-- headline:end -->"


def render_headline(root):
    """The README's headline block: rgbid's CPU row against the peers, from one report."""
    path = root / "docs" / "results" / HEADLINE_REPORT
    with open(path, encoding="utf-8") as f:
        doc = json.load(f)
    versions = doc.get("peer_versions") or {}
    rows = doc.get("rows", [])
    peers = [r["method"] for r in rows if r.get("peer")]
    first_peer = peers[0] if peers else None
    header = [f"{doc.get('sequence_name', '?')} ({doc.get('sequence_frames', '?')} frames)",
              "ATE RMSE m", "RPE m/s", "RPE deg/s", "median ms/frame"]
    if first_peer:
        header.append(f"speed-up vs `{first_peer}`")
    body = []
    for r in rows:
        cells = [
            method_label(r, versions) if r.get("peer") else f"rgbid, {r.get('backend') or r.get('method')} backend",
            num(r.get("ate_rmse_m"), ".4f"),
            num(r.get("rpe_m_per_s"), ".4f"),
            num(r.get("rpe_deg_per_s"), ".3f"),
            num(r.get("ms_median"), ".1f"),
        ]
        if first_peer:
            cells.append("1.00x" if r.get("method") == first_peer
                         else num(r.get("speedup_vs", {}).get(first_peer), ".2f") + "x")
        body.append(cells)
    m = doc.get("meta", {})
    mach = m.get("machine", {})
    dirty = " (with uncommitted changes)" if m.get("dirty") else ""
    out = [HEADLINE_BEGIN]
    out += table(header, body)
    out += [
        "",
        f"Measured {str(m.get('date_utc', '?'))[:10]} at commit `{m.get('commit', '?')}`{dirty} on "
        f"{mach.get('logical_cores', '?')} cores ({mach.get('cpu', '?')}, load average "
        f"{num((m.get('load_average') or [None])[0], '.2f')}), peers in the same run: `{m.get('command', '?')}`. "
        f"Generated by `{COMMAND}` from `docs/results/{HEADLINE_REPORT}`.",
        HEADLINE_END,
    ]
    return "\n".join(out)


def with_headline(readme, block):
    """README text with its headline block replaced by `block`."""
    i, j = readme.find(HEADLINE_BEGIN), readme.find(HEADLINE_END)
    if i < 0 or j < i:
        raise SystemExit(f"README.md has no {HEADLINE_BEGIN} ... {HEADLINE_END} block")
    return readme[:i] + block + readme[j + len(HEADLINE_END):]


def anchor(text):
    """GitHub's heading anchor: lower case, punctuation dropped, spaces to hyphens."""
    keep = "".join(c for c in text.lower() if c.isalnum() or c in " -_")
    return keep.replace(" ", "-")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--check", action="store_true", help="exit 1 if docs/results.md differs from the rendering")
    ap.add_argument("--root", type=pathlib.Path, default=ROOT, help="repository root (default: this checkout)")
    a = ap.parse_args()
    target = a.root / "docs" / "results.md"
    readme = a.root / "README.md"
    outputs = [(target, render(a.root))]
    if (a.root / "docs" / "results" / HEADLINE_REPORT).exists():
        current_readme = readme.read_text(encoding="utf-8")
        outputs.append((readme, with_headline(current_readme, render_headline(a.root))))
    if a.check:
        stale = 0
        for path, text in outputs:
            current = path.read_text(encoding="utf-8") if path.exists() else ""
            if current != text:
                sys.stdout.writelines(difflib.unified_diff(
                    current.splitlines(True), text.splitlines(True), str(path), "rendered"))
                print(f"{path} is out of date: run `{COMMAND}`", file=sys.stderr)
                stale = 1
        return stale
    for path, text in outputs:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")
        print(f"wrote {path} ({len(text.splitlines())} lines)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
