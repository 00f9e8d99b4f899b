"""The search repair at extraction (extraction option `search_repair`, slwarp.neural.search.repair_by_search):
the same trained fields extracted without and with it.

For each scene a field is trained with a preset (default `cpu-hashgrid`, small rig, the 6 random patterns of a
random6+gray7 scan; cached in --cache), then its depth is extracted twice through
slwarp.neural.reconstruct.extract_depth: without and with search_repair. GC(7)/GC(6)-interp of the
same scan's Gray code frames are the yardstick.

    python bench/repair_study.py                                     # rods, torus, steps, bunny; small rig
    python bench/repair_study.py --scenes rods --preset tiny --out /tmp/repair   # a quick look
    python bench/repair_study.py --scenes spheres --rig small-oblique --preset cpu --set refine_range=3 \
        --out bench/results/repair-small-oblique-cpu                # the MLP, refined, on the oblique rig

Writes bench/results/repair-cpu.{json,md} (or --out) and prints the table.
"""
from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "bench"))

from accuracy_sweep import error_split, parse_overrides  # noqa: E402
from study_common import DATE, GRAY_FRAMES, markdown_table, simulate_study_scan, train_cached, write_study  # noqa: E402

COLUMNS = (("mae", "MAE mm", "{:.3f}"), ("mae_within_5mm", "MAE <= 5 mm", "{:.3f}"),
           ("outlier_mae", "MAE part > 5 mm", "{:.3f}"), ("over_5mm", ">5 mm", "{:.2%}"),
           ("completeness", "complete", "{:.1%}"), ("extract_s", "extraction s", "{:.1f}"))


def main(argv=None) -> int:
    from slwarp.decode import reconstruct_depth
    from slwarp.evaluation.metrics import depth_metrics
    from slwarp.neural.extraction import extract_depth

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", default="rods,torus,steps,bunny")
    ap.add_argument("--rig", default="small")
    ap.add_argument("--preset", default="cpu-hashgrid")
    ap.add_argument("--cache", default="/tmp/slwarp-study-fields")
    ap.add_argument("--set", default=None, help="extraction options over the preset's, e.g. 'refine_range=3' (the "
                    "field is trained, or reloaded from --cache, with the preset as it is)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", default=str(REPO / "bench" / "results" / "repair-cpu"), help="output path without suffix")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    doc = {"date": DATE, "machine": platform.processor() or platform.machine(), "args": vars(args), "runs": []}
    for scene in args.scenes.split(","):
        scan, _ = simulate_study_scan(scene, args.rig)
        row = {"scene": scene}
        for name, frames in GRAY_FRAMES.items():
            depth, _, _ = reconstruct_depth(scan, "gc-interp", frames=frames)
            row[name] = {**depth_metrics(depth, scan.gt_depth, scan.mask), **error_split(depth, scan)}
        trainer, cfg, row["train_s"] = train_cached(scan.select("rand*"), args.preset, "base", Path(args.cache),
                                                    key=f"{scene}-{args.rig}")
        for name, repair in (("no repair", False), ("search_repair", True)):
            trainer.cfg = cfg.with_options(**{**parse_overrides(args.set), "search_repair": repair})
            t0 = time.perf_counter()
            depth, _, _, timings, _ = extract_depth(trainer, valid=trainer.renderer.valid_map.cpu().numpy())
            row[name] = {**depth_metrics(depth, scan.gt_depth, scan.mask), **error_split(depth, scan),
                         "extract_s": time.perf_counter() - t0, "repair_s": timings.get("repair_s", 0.0),
                         "repair": timings.get("repair")}
        doc["runs"].append(row)
        p, r = row["no repair"], row["search_repair"]
        print(f"{scene:8s} no repair MAE {p['mae']:.3f} complete {p['completeness']:.3f} | repair MAE {r['mae']:.3f} "
              f"complete {r['completeness']:.3f} ({r['repair_s']:.1f} s) | GC7 {row['GC(7) interp']['mae']:.3f} "
              f"complete {row['GC(7) interp']['completeness']:.3f}", flush=True)
    write_study(args.out, doc, render_markdown)
    return 0


def render_markdown(doc: dict) -> str:
    a = doc["args"]
    md = [f"# Search repair at extraction ({a['preset']} preset, {a['rig']} rig, CPU, {doc['date']})", "",
          f"`python bench/repair_study.py --scenes {a['scenes']} --rig {a['rig']} --preset {a['preset']}"
          + (f" --set {a['set']}" if a.get("set") else "") + "`: the same "
          "trained field extracted without and with `search_repair`; metrics over the GT mask.", ""]
    methods = ("GC(7) interp", "GC(6) interp", "no repair", "search_repair")
    for key, title, fmt in COLUMNS:
        rows = []
        for m in methods:
            vals = [r[m].get(key) for r in doc["runs"]]
            if all(v is None for v in vals):
                continue
            cells = [fmt.format(v) if v is not None else "-" for v in vals]
            mean = np.mean([v for v in vals if v is not None])
            rows.append([m] + cells + [fmt.format(mean)])
        if rows:
            header = ["method"] + [r["scene"] for r in doc["runs"]] + ["mean"]
            md += [f"{title}:", ""] + markdown_table(header, rows) + [""]
    return "\n".join(md) + "\n"


if __name__ == "__main__":
    sys.exit(main())
