"""Classical structured-light baselines on the six built-in scenes, against exact ground truth.

One simulated scan per scene (default rig and noise unless told otherwise) with the patterns
gray7inv+gt+gray7+cgc6+cgc7+hpmp6+npmp6; each baseline decodes only its own frames (selected by name, as
`slwarp decode --frames` does) and is triangulated with the column plane; points outside the scan's depth
range (450 to 1100 mm) are invalid, as `slwarp decode` does by default (two rows show PMP without that
filter). Metrics over the scan's GT mask (hit and lit pixels): MAE, RMSE, median, share above 1 / 2 / 5 mm,
completeness.

    python bench/classical_baselines.py                      # default rig, writes bench/results/classical-cpu.*
    python bench/classical_baselines.py --rig small --out /tmp/classical-small

Writes <out>.json (every number, per scene) and <out>.md (the tables), and prints the markdown.
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
PATTERNS = "gray7inv+gt+gray7+cgc6+cgc7+hpmp6+npmp6"
DATE = "2026-11-22"


def baselines(width: int) -> list[tuple[str, str, str, dict]]:
    """(row label, method, frame selection, params): the paper's baselines and the GT pipeline."""
    return [
        ("GT pipeline (GC7+inv, 4-step 40 px)", "gt", "gc_col_b[0-6],gc_col_b[0-6]_inv,ps_col_p40_*", {}),
        ("GC(7) interp", "gc-interp", "gc_col_b[0-6]", {}),
        ("GC(6) interp", "gc-interp", "gc_col_b[0-5]", {}),
        ("GC(7) stripe centre", "gc", "gc_col_b[0-6]", {}),
        ("CGC(6): 3 GC + 3-step W/4", "cgc", f"gc_col_b[0-2],ps_col_p{width / 4:g}_*", {}),
        ("CGC(7): 4 GC + 3-step W/8", "cgc", f"gc_col_b[0-3],ps_col_p{width / 8:g}_*", {}),
        ("H-PMP(6): 3-step W + 80 px", "hpmp", f"ps_col_p{width:g}_*,ps_col_p80_*", {}),
        ("N-PMP(6): 3-step 48 + 70 px", "npmp", "ps_col_p48_*,ps_col_p70_*", {}),
        # the same GC baselines with the plain fallback (stripe centre outside pairs of transitions)
        ("GC(7) interp, centre fallback", "gc-interp", "gc_col_b[0-6]", {"fallback": "center"}),
        ("GC(6) interp, centre fallback", "gc-interp", "gc_col_b[0-5]", {"fallback": "center"}),
        # without the scan's depth range as a validity filter: wrong period orders stay in the map
        ("H-PMP(6), no depth-range filter", "hpmp", f"ps_col_p{width:g}_*,ps_col_p80_*", {"depth_range": None}),
        ("N-PMP(6), no depth-range filter", "npmp", "ps_col_p48_*,ps_col_p70_*", {"depth_range": None}),
    ]


def cpu_name() -> str:
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rig", default="default", choices=["default", "small"])
    ap.add_argument("--scenes", default=None, help="comma-separated scenes (default: all six)")
    ap.add_argument("--device", default=None, help="simulator device (cpu, cuda:0; default: CUDA when present)")
    ap.add_argument("--seed", type=int, default=0, help="simulator noise seed")
    ap.add_argument("--out", default=str(REPO / "bench" / "results" / "classical-cpu"), help="output path without suffix")
    args = ap.parse_args(argv)

    import os

    from slwarp.decode import reconstruct_depth
    from slwarp.evaluation.metrics import METRIC_COLUMNS, depth_metrics, format_table
    from slwarp.sim.scenes import SCENE_NAMES
    from slwarp.sim.simulate import SimOptions, simulate_scene

    scenes = args.scenes.split(",") if args.scenes else list(SCENE_NAMES)
    options = SimOptions(seed=args.seed)
    results: dict = {}
    timings: dict = {}
    for scene in scenes:
        t0 = time.perf_counter()
        scan = simulate_scene(scene, PATTERNS, args.rig, options, device=args.device)
        t_sim = time.perf_counter() - t0
        rows = baselines(scan.projector.width)
        timings[scene] = {"simulate_s": t_sim}
        for label, method, frames, params in rows:
            t1 = time.perf_counter()
            depth, _, dec = reconstruct_depth(scan, method, frames=frames, **params)
            m = depth_metrics(depth, scan.gt_depth, scan.mask)
            m.update(frames=len(dec.frames), decode_s=dec.extra["decode_s"], triangulate_s=dec.extra["triangulate_s"])
            results.setdefault(label, {})[scene] = m
            print(f"{scene:8s} {label:36s} MAE {m['mae']:7.3f} mm  >1 {m['over_1mm']:.3f}  >5 {m['over_5mm']:.3f}  "
                  f"complete {m['completeness']:.4f}  ({time.perf_counter() - t1:.1f} s)", file=sys.stderr, flush=True)
        print(f"{scene}: simulated in {t_sim:.1f} s", file=sys.stderr, flush=True)

    # per-method averages over scenes (the mean of per-scene metrics, as papers report)
    summary = {}
    for label, per in results.items():
        keys = ["mae", "rmse", "median", "over_1mm", "over_2mm", "over_5mm", "completeness"]
        summary[label] = {k: float(np.mean([per[s][k] for s in scenes])) for k in keys}
        summary[label]["n_valid"] = int(np.sum([per[s]["n_valid"] for s in scenes]))
        summary[label]["frames"] = per[scenes[0]]["frames"]
    machine = f"{cpu_name()}, {os.cpu_count()} logical CPUs"
    head = (f"Classical baselines, {args.rig} rig, SimOptions() (noise, defocus, 8 bit; seed {args.seed}), "
            f"scenes {', '.join(scenes)}; {machine}; {DATE}. Metrics over the GT mask; means over scenes.")
    cols = [("frames", "patterns", "{:d}")] + [c for c in METRIC_COLUMNS if c[0] != "n_valid"]
    md = [f"# Classical baselines\n\n{head}\n", format_table(summary, cols, "method"), "",
          "MAE (mm) per scene:", ""]
    per_scene_cols = [(s, s, "{:.3f}") for s in scenes] + [("mean", "mean", "{:.3f}")]
    per_rows = [(label, {**{s: results[label][s]["mae"] for s in scenes}, "mean": summary[label]["mae"]})
                for label in results]
    md.append(format_table(per_rows, per_scene_cols, "method"))
    text = "\n".join(md) + "\n"
    print(text)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".md").write_text(text)
    doc = {"date": DATE, "machine": machine, "rig": args.rig, "patterns": PATTERNS, "options": options.__dict__,
           "scenes": scenes, "summary": summary, "per_scene": results, "timings": timings}
    out.with_suffix(".json").write_text(json.dumps(doc, indent=2, default=float) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
