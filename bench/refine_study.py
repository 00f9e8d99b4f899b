"""The photometric refinement (extraction option `refine_range`, slwarp.neural.pattern_model.refine_depth)
against today's extraction, on the same trained fields.

For each scene a field is trained with a preset (default `cpu`, small rig, the 6 random patterns of a
random6+gray7 scan; cached in --cache, shared with bench/train_ablation.py's baseline fields), then its depth
is extracted twice through slwarp.neural.reconstruct.extract_depth: as the preset says (refine_range 0) and
with refine_range set; GC(7)/GC(6)-interp of the same scan's Gray code frames are the yardstick.

    python bench/refine_study.py                                   # bunny, torus, checker, rods; small rig
    python bench/refine_study.py --scenes bunny --preset tiny --out /tmp/refine   # a quick look

Writes bench/results/refine-cpu.{json,md} (or --out) and prints the table.
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "bench"))

from study_common import DATE, gray_code_yardstick, markdown_table, simulate_study_scan, train_cached  # noqa: E402

KEYS = (("mae", "MAE mm", "{:.3f}"), ("median", "median mm", "{:.3f}"), ("over_5mm", ">5 mm", "{:.2%}"),
        ("completeness", "complete", "{:.1%}"))


def main(argv=None) -> int:
    from slwarp.evaluation.metrics import depth_metrics
    from slwarp.neural.reconstruct import extract_depth

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", default="bunny,torus,checker,rods")
    ap.add_argument("--rig", default="small")
    ap.add_argument("--camera", default="linear", help="camera model (slwarp.sim.simulate.CAMERA_MODELS)")
    ap.add_argument("--preset", default="cpu")
    ap.add_argument("--refine-range", type=float, default=3.0, help="refine_range of the refined extraction (mm)")
    ap.add_argument("--cache", default="/tmp/slwarp-study-fields")
    ap.add_argument("--out", default=str(REPO / "bench" / "results" / "refine-cpu"))
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    doc = {"date": DATE, "machine": platform.processor() or platform.machine(), "args": vars(args), "runs": []}
    for scene in args.scenes.split(","):
        scan, _ = simulate_study_scan(scene, args.rig, args.camera)
        gray = gray_code_yardstick(scan)
        trainer, cfg, train_s = train_cached(scan.select("rand*"), args.preset, "baseline", Path(args.cache),
                                             key=f"{args.rig}-{args.camera}-{scene}")
        row = {"scene": scene, "gray": gray, "train_s": train_s}
        for name, rr in (("today", 0.0), ("refined", args.refine_range)):
            trainer.cfg = cfg.with_options(refine_range=rr)
            t0 = time.perf_counter()
            depth, _, _, _ = extract_depth(trainer, valid=trainer.renderer.valid_map.cpu().numpy())
            row[name] = {**depth_metrics(depth, scan.gt_depth, scan.mask), "extract_s": time.perf_counter() - t0}
        doc["runs"].append(row)
        t, r = row["today"], row["refined"]
        print(f"{scene:8s} today MAE {t['mae']:.3f} median {t['median']:.3f} | refined MAE {r['mae']:.3f} median "
              f"{r['median']:.3f} ({r['extract_s'] - t['extract_s']:.0f} s more) | GC7 {gray['GC(7) interp']['mae']:.3f}",
              flush=True)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(doc, indent=1, default=float))
    md = render_markdown(doc)
    out.with_suffix(".md").write_text(md)
    print(md)
    return 0


def render_markdown(doc: dict) -> str:
    a = doc["args"]
    lines = ["# Photometric refinement at extraction (refine_range) against today's extraction", "",
             f"`python bench/refine_study.py --scenes {a['scenes']} --rig {a['rig']} --camera {a['camera']} --preset "
             f"{a['preset']} --refine-range {a['refine_range']}` ({doc['date']}, CPU, one thread). The same trained field "
             "per scene, extracted with refine_range 0 (today) and with the refinement; GC rows: gc-interp of the "
             "same scan's 7 and 6 most significant column bits.", ""]
    runs = doc["runs"]
    scenes = [r["scene"] for r in runs]
    for key, title, fmt in KEYS:
        rows = []
        for name, label in (("today", "today (refine_range 0)"), ("refined", f"refine_range {a['refine_range']:g}")):
            vals = [r[name][key] for r in runs]
            rows.append([label] + [fmt.format(v) for v in vals] + [fmt.format(float(np.mean(vals)))])
        for g in ("GC(7) interp", "GC(6) interp"):
            vals = [r["gray"][g][key] for r in runs]
            rows.append([f"*{g}*"] + [fmt.format(v) for v in vals] + [fmt.format(float(np.mean(vals)))])
        lines += [f"## {title}", ""] + markdown_table(["extraction"] + scenes + ["mean"], rows) + [""]
    rows = [[r["scene"], f"{r['today']['extract_s']:.1f}", f"{r['refined']['extract_s']:.1f}"] for r in runs]
    lines += ["## extraction seconds (CPU, one thread, shared machine)", ""]
    lines += markdown_table(["scene", "today", "refined"], rows) + [""]
    return "\n".join(lines)


if __name__ == "__main__":
    raise SystemExit(main())
