#!/usr/bin/env python3
"""Collects the thesis-fidelity option runs of scripts/thesis_options.sh into one report,
docs/results/thesis_options.json, rendered by scripts/results.py.

One row per (sequence, variant): rgbid's ATE and RPE, OpenCV RGB_DEPTH's ATE and RPE from the
same script run (the `base` bench run holds the peer), the ratio ATE / OpenCV ATE that the
issue's default rule averages over the sequences, the median compute time per frame, and, for
the sampling variants, the mean Gauss-Newton iterations per level (coarsest first) and the
median `total_ms` of `rgbid odometry --csv` (decoding excluded). Then one row per SLAM
variant: ATE and RPE of `rgbid slam`'s trajectory, the same OpenCV odometry figures for
reference, keyframes, loops and the run's wall time (loading and output included).

Usage:
    python3 scripts/thesis_options.py RUNS_DIR [--out docs/results/thesis_options.json]
Standard library only.
"""
import argparse
import csv
import json
import pathlib
import re
import statistics

SEQUENCES = ["tum_fr1_rpy_0_199", "redkitchen_0_299"]
# (variant, odometry option as given to --set, bench file suffix, odometry CSV suffix)
VARIANTS = [
    ("defaults (covisibility_test=consistent, geometric_sampling=nearest, location=both, linearisation=current)", "base", "base"),
    ("covisibility_test=depth (no occlusion condition of eq. 4.33)", "depthcovis", None),
    ("geometric_sampling=coarselinear", "coarse", "coarse"),
    ("location=zero (no mu of eq. 4.26-4.27)", "loczero", None),
    ("location=photometric", "locphoto", None),
    ("linearisation=reference (eq. 4.16-4.17, 6.12-6.13)", "reflin", None),
]

# `rgbid slam` variants (scripts/thesis_options.sh), ATE after rigid alignment.
SLAM_VARIANTS = [
    ("default", "slam: defaults (fusion 3 sigma_W + occlusion + both directions, weight cap 30)"),
    ("fixedfusion", "slam: fusion tolerance 0.004 + 0.03 rho, keyframe side only"),
    ("nocap", "slam: fusion weight not capped (max_weight 1e9 instead of 30)"),
    ("loczero", "slam: odometry location=zero"),
    ("reflin", "slam: odometry linearisation=reference"),
]


def bench_rows(path):
    with open(path, encoding="utf-8") as f:
        doc = json.load(f)
    rows = {r["method"]: r for r in doc["rows"]}
    return doc, rows


def csv_stats(path, iterations):
    """Mean iterations per level (coarsest first), median total ms, and frames that ran the
    configured maximum on every level (`iterations`: the config's list, finest first)."""
    levels, total = [], []
    with open(path, encoding="utf-8") as f:
        for r in csv.DictReader(f):
            if r.get("status") != "ok" or not r.get("level_iterations"):
                continue
            levels.append([int(x) for x in r["level_iterations"].split()])
            total.append(float(r["total_ms"]))
    if not levels:
        return None, None, None
    n = max(len(v) for v in levels)
    mean = [statistics.mean(v[k] for v in levels if len(v) == n) for k in range(n)]
    cap = [iterations[min(n - 1 - k, len(iterations) - 1)] for k in range(n)]
    maxed = sum(1 for v in levels if v == cap)
    return mean, statistics.median(total), maxed


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("runs", type=pathlib.Path)
    ap.add_argument("--out", type=pathlib.Path, default=pathlib.Path("docs/results/thesis_options.json"))
    a = ap.parse_args()
    out_rows, meta = [], None
    for seq in SEQUENCES:
        base_doc, base = bench_rows(a.runs / f"{seq}-base.json")
        meta = meta or base_doc["meta"]
        cv = base.get("cv_rgbd", {})
        for label, suffix, csv_suffix in VARIANTS:
            doc, rows = bench_rows(a.runs / f"{seq}-{suffix}.json")
            r = rows["rgbid cpu"]
            row = {
                "sequence": seq,
                "variant": label,
                "ate_m": r["ate_rmse_m"],
                "rpe_m_per_s": r["rpe_m_per_s"],
                "opencv_ate_m": cv.get("ate_rmse_m"),
                "opencv_rpe_m_per_s": cv.get("rpe_m_per_s"),
                "ate_over_opencv": r["ate_rmse_m"] / cv["ate_rmse_m"] if cv.get("ate_rmse_m") else None,
                "bench_ms_median": r["ms_median"],
                "opencv_ms_median": cv.get("ms_median"),
            }
            if csv_suffix:
                mean, total, maxed = csv_stats(a.runs / f"{seq}-{csv_suffix}.csv", doc["config"]["iterations"])
                row["iterations_per_level_mean"] = " / ".join(f"{m:.2f}" for m in mean) if mean else None
                row["frames_at_max_iterations_every_level"] = maxed
                row["odometry_total_ms_median"] = total
            out_rows.append(row)
    for seq in SEQUENCES:
        _, base = bench_rows(a.runs / f"{seq}-base.json")
        cv = base.get("cv_rgbd", {})
        for v, label in SLAM_VARIANTS:
            with open(a.runs / f"slam-{seq}-{v}.eval.json", encoding="utf-8") as f:
                ev = json.load(f)
            log = (a.runs / f"slam-{seq}-{v}.log").read_text(encoding="utf-8")
            ate = ev["ate"]["translation"]["rmse"]
            out_rows.append({
                "sequence": seq,
                "variant": label,
                "ate_m": ate,
                "rpe_m_per_s": ev["rpe"]["translation_m"]["rmse"],
                "opencv_ate_m": cv.get("ate_rmse_m"),
                "opencv_rpe_m_per_s": cv.get("rpe_m_per_s"),
                "ate_over_opencv": ate / cv["ate_rmse_m"] if cv.get("ate_rmse_m") else None,
                "slam_keyframes": int(re.search(r"keyframes (\d+)", log).group(1)),
                "slam_loops": int(re.search(r"loops (\d+) accepted", log).group(1)),
                "slam_wall_s": float(re.search(r"([0-9.]+) s wall", log).group(1)),
            })
    meta = dict(meta)
    meta["command"] = ("scripts/thesis_options.sh (rgbid bench odometry, rgbid odometry --csv and "
                       "rgbid slam per variant), then python3 scripts/thesis_options.py")
    report = {"benchmark": "thesis-options", "meta": meta, "rows": out_rows}
    a.out.parent.mkdir(parents=True, exist_ok=True)
    with open(a.out, "w", encoding="utf-8") as f:
        json.dump(report, f, indent=1)
        f.write("\n")
    for row in out_rows:
        print(row)


if __name__ == "__main__":
    main()
