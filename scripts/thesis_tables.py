#!/usr/bin/env python3
"""Collects the runs of scripts/thesis_tables.sh into docs/results/thesis_tables.json, the
analogues of the thesis' tables 4.1 (robust estimator x depth or inverse depth x ML or MAD
scale, plus the Gaussian-consistent M-scale for Huber and Tukey), 4.2 (photometric, geometric
or both terms), 4.3 (performance options with their time) and 6.1 (odometry, SLAM without
loop closure, SLAM with loop closure) on the two real sequences, rendered by scripts/results.py.

Each odometry row holds rgbid's ATE, translational and rotational RPE and median compute time
per frame (`rgbid bench odometry`), and the ratios to OpenCV RGB_DEPTH measured in the same
script run. Table 6.1's SLAM rows come from one `rgbid slam` run: `odometry.txt` is the
front-end's trajectory (frame-to-keyframe tracking on fused keyframes; without loop closure the
pose graph holds only the sequential edges it already satisfies), `trajectory.txt` the one after
loop closure.

Usage:
    python3 scripts/thesis_tables.py RUNS_DIR [--out docs/results/thesis_tables.json]
Standard library only.
"""
import argparse
import json
import pathlib
import re

SEQUENCES = ["tum_fr1_rpy_0_199", "redkitchen_0_299"]
ESTIMATORS = ["student", "huber", "tukey", "leastsquares"]
PARAMS = [("inversedepth", "inverse depth"), ("depth", "depth")]
SCALES = [("ml", "ML"), ("mad", "MAD"), ("mscale", "Gaussian-consistent M-")]
T43 = [
    ("default", "default (3 levels optimised up to 320 px wide, 6/8/10 iterations, 19200 samples)"),
    ("t43-levels3", "levels = 3"),
    ("t43-full-resolution", "max_width = 0 (the 640x480 level optimised too)"),
    ("t43-stop-level2", "stop_level = 2 (finest level 160x120)"),
    ("t43-samples4800", "max_samples = 4800 (scale estimation sample)"),
    ("t43-iterations-halved", "iterations = [3, 4, 5]"),
    ("t43-frame-to-frame", "reference_switch = null (frame-to-frame)"),
    ("t43-no-constant-velocity", "constant_velocity = false"),
]


def bench(runs, seq, name):
    path = runs / f"{seq}-{name}.json"
    if not path.exists():
        return None, None
    with open(path, encoding="utf-8") as f:
        doc = json.load(f)
    rows = {r["method"]: r for r in doc["rows"]}
    return doc, rows


def odo_row(table, seq, variant, r, cv):
    def ratio(a, b):
        return a / b if a is not None and b else None
    return {
        "table": table,
        "sequence": seq,
        "variant": variant,
        "ate_m": r["ate_rmse_m"],
        "rpe_m_per_s": r["rpe_m_per_s"],
        "rpe_deg_per_s": r.get("rpe_deg_per_s"),
        "ms_median": r["ms_median"],
        "ate_over_opencv": ratio(r["ate_rmse_m"], cv.get("ate_rmse_m")),
        "opencv_ms_over_ms": ratio(cv.get("ms_median"), r["ms_median"]),
    }


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("runs", type=pathlib.Path)
    ap.add_argument("--out", type=pathlib.Path, default=pathlib.Path("docs/results/thesis_tables.json"))
    a = ap.parse_args()
    out_rows, meta, missing = [], None, []
    peers = {}
    for seq in SEQUENCES:
        doc, rows = bench(a.runs, seq, "default")
        if doc is None:
            raise SystemExit(f"{a.runs}/{seq}-default.json is missing: run scripts/thesis_tables.sh first")
        meta = meta or doc["meta"]
        cv = rows.get("cv_rgbd", {})
        peers[seq] = cv
        out_rows.append({"table": "peer", "sequence": seq, "variant": "OpenCV RGB_DEPTH",
                         "ate_m": cv.get("ate_rmse_m"), "rpe_m_per_s": cv.get("rpe_m_per_s"),
                         "rpe_deg_per_s": cv.get("rpe_deg_per_s"), "ms_median": cv.get("ms_median"),
                         "ate_over_opencv": 1.0, "opencv_ms_over_ms": 1.0})

        def add(table, name, label):
            d, rs = (doc, rows) if name == "default" else bench(a.runs, seq, name)
            if d is None or "rgbid cpu" not in rs:
                missing.append(f"{seq}-{name}")
                return
            out_rows.append(odo_row(table, seq, label, rs["rgbid cpu"], cv))

        for est in ESTIMATORS:
            for geo, geo_label in PARAMS:
                for sc, sc_label in SCALES:
                    if sc == "mscale" and est in ("student", "leastsquares"):
                        continue
                    add("4.1", f"t41-{est}-{geo}-{sc}", f"{est}, {geo_label}, {sc_label} scale")
        add("4.2", "t42-photometric", "photometric only")
        add("4.2", "t42-geometric", "geometric only")
        add("4.2", "default", "photometric + geometric (default)")
        for name, label in T43:
            add("4.3", name, label)
        add("6.1", "default", "odometry (`rgbid odometry`)")
        log_path = a.runs / f"slam-{seq}.log"
        if log_path.exists():
            log = log_path.read_text(encoding="utf-8")
            wall = re.search(r"([0-9.]+) s wall", log)
            for t, label in [("odometry", "SLAM front-end, no loop closure (`odometry.txt`)"),
                             ("trajectory", "SLAM with loop closure (`trajectory.txt`)")]:
                with open(a.runs / f"slam-{seq}-{t}.eval.json", encoding="utf-8") as f:
                    ev = json.load(f)
                ate = ev["ate"]["translation"]["rmse"]
                out_rows.append({
                    "table": "6.1", "sequence": seq, "variant": label, "ate_m": ate,
                    "rpe_m_per_s": ev["rpe"]["translation_m_per_s"]["rmse"],
                    "rpe_deg_per_s": ev["rpe"]["rotation_deg_per_s"]["rmse"],
                    "ms_median": None,
                    "ate_over_opencv": ate / cv["ate_rmse_m"] if cv.get("ate_rmse_m") else None,
                    "opencv_ms_over_ms": None,
                    "slam_wall_s": float(wall.group(1)) if wall else None,
                })
        else:
            missing.append(f"slam-{seq}")
    meta = dict(meta)
    meta["command"] = "scripts/thesis_tables.sh (rgbid bench odometry per variant, rgbid slam), then python3 scripts/thesis_tables.py"
    load = [(a.runs / n).read_text(encoding="utf-8").strip() for n in ("load_start.txt", "load_end.txt")
            if (a.runs / n).exists()]
    meta["load"] = " / ".join(load)
    report = {"benchmark": "thesis-tables", "meta": meta, "rows": out_rows, "missing": missing}
    a.out.parent.mkdir(parents=True, exist_ok=True)
    with open(a.out, "w", encoding="utf-8") as f:
        json.dump(report, f, indent=1)
        f.write("\n")
    for row in out_rows:
        print(row)
    if missing:
        print("missing runs:", ", ".join(missing))


if __name__ == "__main__":
    main()
