"""Classical structured-light baselines on every rig geometry and built-in scene, against exact ground truth.

One simulated scan per rig and scene (noise on, `SimOptions()`), with the classical pattern sets along the
projector axis that carries depth on that rig (columns on `default`, `oblique` and `rolled`, rows on `vertical`:
`slwarp.decode.choose_plane_axis`) plus the 7-bit Gray code of the other axis. Each baseline decodes only its
own frames, selected by role (as `slwarp decode --frames` does), triangulated as `slwarp decode` does by
default (`--triangulation auto`: the plane of the depth-carrying axis, or both coordinates on the oblique rig
when both codes are decoded), points outside the scan's depth range (450 to 1100 mm) invalid. Metrics over the
scan's GT mask (hit and lit pixels): MAE, RMSE, median, share above 1 / 2 / 5 mm, completeness.

    python -m bench.classical_baselines                          # every geometry, full resolution
    python -m bench.classical_baselines --rigs default,rolled --scenes bunny,torus --small --out /tmp/c

Writes <out>.json (every number, per rig and scene) and <out>.md (the tables), and prints the markdown.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DATE = "2026-11-22"
SETS = "gt+cgc6+cgc7+hpmp6+npmp6"  # gt = 7 Gray code bits with inverses + 4-step at 40 px: GC(6), GC(7) come from it


def patterns_for(axis: str) -> str:
    """The classical sets along `axis` and the 7 Gray code bits of the other axis."""
    if axis == "col":
        return SETS + "+gray7_row"
    return "+".join(f"{s}_row" for s in SETS.split("+")) + "+gray7"


def baselines(axis: str, size: int) -> list[tuple[str, str, str]]:
    """(row label, method, frame selection by role) of the baselines along `axis` of `size` projector px
    (S in the labels: the projector's width for column codes, its height for row codes)."""
    other = "row" if axis == "col" else "col"
    return [
        ("GT pipeline (GC7+inv, 4-step 40 px)", "gt", f"gray:{axis}:bit=0-6,phase:{axis}:period=40"),
        ("GC(7) interp", "gc-interp", f"gray:{axis}:bit=0-6:noinv"),
        ("GC(6) interp", "gc-interp", f"gray:{axis}:bit=0-5:noinv"),
        ("GC(7) stripe centre", "gc", f"gray:{axis}:bit=0-6:noinv"),
        ("CGC(6): 3 GC + 3-step S/4", "cgc", f"gray:{axis}:bit=0-2:noinv,phase:{axis}:period={size / 4:g}"),
        ("CGC(7): 4 GC + 3-step S/8", "cgc", f"gray:{axis}:bit=0-3:noinv,phase:{axis}:period={size / 8:g}"),
        ("H-PMP(6): 3-step S + 80 px", "hpmp", f"phase:{axis}:period={size:g},phase:{axis}:period=80"),
        ("N-PMP(6): 3-step 48 + 70 px", "npmp", f"phase:{axis}:period=48,phase:{axis}:period=70"),
        ("GC(7) interp, column + row codes (14)", "gc-interp", f"gray:{axis}:bit=0-6:noinv,gray:{other}:bit=0-6:noinv"),
    ]


def cpu_name() -> str:
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


KEYS = ["mae", "rmse", "median", "over_1mm", "over_2mm", "over_5mm", "completeness"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rigs", default=None, help="comma-separated rig geometries (default: all: default, vertical, "
                                                 "oblique, rolled)")
    ap.add_argument("--small", action="store_true", help="use each geometry's small-resolution rig")
    ap.add_argument("--scenes", default=None, help="comma-separated scenes (default: all six)")
    ap.add_argument("--device", default=None, help="simulator device (cpu, cuda:0; default: CUDA when present)")
    ap.add_argument("--seed", type=int, default=0, help="simulator noise seed")
    ap.add_argument("--out", default=str(REPO / "bench" / "results" / "classical-cpu"), help="output path without suffix")
    args = ap.parse_args(argv)

    from slwarp.decode import choose_plane_axis, reconstruct_depth
    from slwarp.evaluation.metrics import METRIC_COLUMNS, depth_metrics, format_table
    from slwarp.sim.rigs import GEOMETRIES, make_rig, rig_name
    from slwarp.sim.scenes import SCENE_NAMES
    from slwarp.sim.simulate import SimOptions, simulate_scene

    geometries = args.rigs.split(",") if args.rigs else list(GEOMETRIES)
    scenes = args.scenes.split(",") if args.scenes else list(SCENE_NAMES)
    options = SimOptions(seed=args.seed)
    doc_rigs: dict = {}
    t_start = time.perf_counter()
    for geometry in geometries:
        rig = rig_name(geometry, args.small)
        _, projector = make_rig(rig)
        axis = choose_plane_axis(projector)
        size = projector.width if axis == "col" else projector.height
        rows = baselines(axis, size)
        patterns = patterns_for(axis)
        results: dict = {}
        timings: dict = {}
        for scene in scenes:
            t0 = time.perf_counter()
            scan = simulate_scene(scene, patterns, rig, options, device=args.device)
            timings[scene] = {"simulate_s": time.perf_counter() - t0}
            for label, method, frames in rows:
                t1 = time.perf_counter()
                depth, _, dec = reconstruct_depth(scan, method, frames=frames)
                m = depth_metrics(depth, scan.gt_depth, scan.mask)
                m.update(frames=len(dec.frames), triangulation=dec.extra["triangulation"],
                         decode_s=dec.extra["decode_s"], triangulate_s=dec.extra["triangulate_s"])
                results.setdefault(label, {})[scene] = m
                print(f"{rig:14s} {scene:8s} {label:38s} MAE {m['mae']:7.3f} mm  >5 {m['over_5mm']:.4f}  "
                      f"complete {m['completeness']:.4f}  {m['triangulation']:5s} ({time.perf_counter() - t1:.1f} s)",
                      file=sys.stderr, flush=True)
            print(f"{rig}/{scene}: simulated in {timings[scene]['simulate_s']:.1f} s; "
                  f"{time.perf_counter() - t_start:.0f} s so far", file=sys.stderr, flush=True)
        summary = {}
        for label, per in results.items():  # the mean of per-scene metrics, as papers report
            summary[label] = {k: float(np.mean([per[s][k] for s in scenes])) for k in KEYS}
            summary[label]["n_valid"] = int(np.sum([per[s]["n_valid"] for s in scenes]))
            summary[label]["frames"] = per[scenes[0]]["frames"]
            summary[label]["triangulation"] = per[scenes[0]]["triangulation"]
        doc_rigs[rig] = {"geometry": geometry, "axis": axis, "patterns": patterns, "summary": summary,
                         "per_scene": results, "timings": timings}

    machine = f"{cpu_name()}, {os.cpu_count()} logical CPUs"
    command = " ".join(["python -m bench.classical_baselines"] + list(sys.argv[1:] if argv is None else argv))
    total_s = time.perf_counter() - t_start
    rigs = list(doc_rigs)
    labels = list(next(iter(doc_rigs.values()))["summary"])
    head = (f"Classical baselines on {', '.join(rigs)}; SimOptions() (noise, defocus, 8 bit; seed {args.seed}); "
            f"scenes {', '.join(scenes)}; {machine}; {DATE}; {total_s / 60:.1f} min "
            f"(`{command}`). Each rig's codes run along "
            "the projector axis that carries depth there (columns on default, oblique, rolled; rows on vertical). "
            "S: the projector's size along the coded axis. Metrics over the GT mask; means over scenes.")
    md = [f"# Classical baselines on every rig\n\n{head}\n", "Mean MAE (mm) over scenes, per rig:", ""]
    mae_cols = [(r, r, "{:.3f}") for r in rigs]
    md.append(format_table([(lab, {r: doc_rigs[r]["summary"][lab]["mae"] for r in rigs}) for lab in labels],
                           mae_cols, "method"))
    md += ["", "Share of pixels with error above 5 mm, per rig:", ""]
    md.append(format_table([(lab, {r: doc_rigs[r]["summary"][lab]["over_5mm"] for r in rigs}) for lab in labels],
                           [(r, r, "{:.2%}") for r in rigs], "method"))
    cols = [("frames", "patterns", "{:d}"), ("triangulation", "triangulation", "{}")] + \
        [c for c in METRIC_COLUMNS if c[0] != "n_valid"]
    per_scene_cols = [(s, s, "{:.3f}") for s in scenes] + [("mean", "mean", "{:.3f}")]
    for r in rigs:
        d = doc_rigs[r]
        md += ["", f"## {r} ({d['geometry']}; codes along projector {d['axis']}s; patterns {d['patterns']})", "",
               format_table(d["summary"], cols, "method"), "", "MAE (mm) per scene:", ""]
        md.append(format_table([(lab, {**{s: d["per_scene"][lab][s]["mae"] for s in scenes}, "mean": d["summary"][lab]["mae"]})
                                for lab in labels], per_scene_cols, "method"))
    text = "\n".join(md) + "\n"
    print(text)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".md").write_text(text)
    doc = {"date": DATE, "machine": machine, "command": command,
           "options": options.__dict__, "scenes": scenes, "total_s": total_s, "rigs": doc_rigs}
    out.with_suffix(".json").write_text(json.dumps(doc, indent=1, default=float) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
