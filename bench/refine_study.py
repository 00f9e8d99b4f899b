"""The photometric refinement (extraction option `refine_range`, slwarp.neural.pattern_model.refine_depth)
against today's extraction, on the same trained fields.

For each scene a field is trained with a preset (default `cpu`, small rig, the 6 random patterns of a
random6+gray7 scan; cached in --cache, shared with bench/train_ablation.py's baseline fields), then its depth
is extracted twice through slwarp.neural.reconstruct.extract_depth: as the preset says (refine_range 0) and
with refine_range set; GC(7)/GC(6)-interp of the same scan's Gray code frames are the yardstick.

    python bench/refine_study.py                                   # bunny, torus, checker, rods; small rig
    python bench/refine_study.py --scenes bunny --preset tiny --out /tmp/refine   # a quick look

Writes bench/results/refine-cpu.{json,md} (or --out) and prints the table.

--time-only: no training; the refinement alone (refine_depth, --refine-range, 0.05 mm steps) of each scene's
ground-truth depth plus a smooth error (0.4 to 1.2 mm over the image), timed on --device (CUDA synchronised,
the best of --repeat runs), with its peak CUDA memory and the MAE before and after; --reference also times the
host (numpy, cv2) implementation it replaced (tests/test_pattern_model.py) and compares the depths:

    python bench/refine_study.py --time-only --rig default --device cuda            # the lead's GPU timing
    python bench/refine_study.py --time-only --scenes bunny --reference             # CPU, small rig, old vs new

Writes bench/results/refine-time-<rig>-<device>.json (or --out .json) and prints a table.
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

from study_common import (DATE, gray_code_yardstick, markdown_table, simulate_study_scan,  # noqa: E402
                          train_cached, write_study)

KEYS = (("mae", "MAE mm", "{:.3f}"), ("median", "median mm", "{:.3f}"), ("over_5mm", ">5 mm", "{:.2%}"),
        ("completeness", "complete", "{:.1%}"))


def main(argv=None) -> int:
    from slwarp.evaluation.metrics import depth_metrics
    from slwarp.neural.extraction import extract_depth

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", default="bunny,torus,checker,rods")
    ap.add_argument("--rig", default="small")
    ap.add_argument("--camera", default="linear", help="camera model (slwarp.sim.simulate.CAMERA_MODELS)")
    ap.add_argument("--preset", default="cpu")
    ap.add_argument("--refine-range", type=float, default=3.0, help="refine_range of the refined extraction (mm)")
    ap.add_argument("--cache", default="/tmp/slwarp-study-fields")
    ap.add_argument("--out", default=None, help="output path without suffix (default bench/results/refine-cpu, "
                    "or refine-time-<rig>-<device> with --time-only)")
    ap.add_argument("--time-only", action="store_true", help="time the refinement alone (see the module docstring)")
    ap.add_argument("--device", default="cpu", help="--time-only: device of the refinement")
    ap.add_argument("--chunk", type=int, default=8, help="--time-only: offsets per chunk")
    ap.add_argument("--repeat", type=int, default=2, help="--time-only: runs per scene (the best is reported)")
    ap.add_argument("--reference", action="store_true", help="--time-only: also the host implementation (slow)")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    if args.time_only:
        return time_only(args)
    args.out = args.out or str(REPO / "bench" / "results" / "refine-cpu")
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
            depth = extract_depth(trainer, valid=trainer.renderer.valid_map.cpu().numpy()).depth
            row[name] = {**depth_metrics(depth, scan.gt_depth, scan.mask), "extract_s": time.perf_counter() - t0}
        doc["runs"].append(row)
        t, r = row["today"], row["refined"]
        print(f"{scene:8s} today MAE {t['mae']:.3f} median {t['median']:.3f} | refined MAE {r['mae']:.3f} median "
              f"{r['median']:.3f} ({r['extract_s'] - t['extract_s']:.0f} s more) | GC7 {gray['GC(7) interp']['mae']:.3f}",
              flush=True)
    write_study(args.out, doc, render_markdown)
    return 0


def smooth_error(shape) -> np.ndarray:
    """[H, W] mm: 0.8 + 0.4 sin cos, 0.4 to 1.2 mm, a few periods over the image whatever its resolution."""
    y, x = np.indices(shape)
    return 0.8 + 0.4 * np.sin(8.0 * x / shape[1]) * np.cos(10.0 * y / shape[0])


def time_only(args) -> int:
    from slwarp.evaluation.metrics import depth_metrics
    from slwarp.neural.pattern_model import refine_depth

    reference = None
    if args.reference:
        sys.path.insert(0, str(REPO / "tests"))
        from test_pattern_model import _ref_refine_depth as reference
    dev = torch.device(args.device)
    cuda = dev.type == "cuda"

    def timed(fn):
        best, out = float("inf"), None
        for _ in range(max(1, args.repeat)):
            if cuda:
                torch.cuda.synchronize(dev)
            t0 = time.perf_counter()
            out = fn()  # numpy out: the result is on the host, the device synchronised
            best = min(best, time.perf_counter() - t0)
        return out, best

    doc = {"date": DATE, "machine": platform.processor() or platform.machine(), "torch": torch.__version__,
           "device": torch.cuda.get_device_name(dev) if cuda else "cpu", "args": vars(args), "runs": []}
    for scene in args.scenes.split(","):
        scan, _ = simulate_study_scan(scene, args.rig, args.camera)
        scan = scan.select("rand*")
        ok = np.isfinite(scan.gt_depth) & (scan.mask if scan.mask is not None else True)
        start = np.where(ok, scan.gt_depth + smooth_error(ok.shape), np.nan).astype(np.float32)
        call = (start, scan.camera, scan.projector, scan.images, scan.patterns, args.refine_range)
        if cuda:
            torch.cuda.reset_peak_memory_stats(dev)
        new, new_s = timed(lambda: refine_depth(*call, device=dev, chunk=args.chunk))
        row = {"scene": scene, "pixels": int(ok.sum()), "frames": int(scan.images.shape[0]),
               "size": list(scan.gt_depth.shape), "offsets": int(round(2 * args.refine_range / 0.05)) + 1,
               "before": depth_metrics(start, scan.gt_depth, scan.mask),
               "refined": depth_metrics(new, scan.gt_depth, scan.mask), "refine_s": new_s,
               "peak_cuda_gb": torch.cuda.max_memory_allocated(dev) / 2**30 if cuda else None}
        if reference is not None:
            old, old_s = timed(lambda: reference(*call))
            sel = np.isfinite(old)
            diff = np.abs(new - old)[sel]
            row["reference"] = {**depth_metrics(old, scan.gt_depth, scan.mask), "refine_s": old_s,
                                "diff_median_mm": float(np.median(diff)), "diff_p99_mm": float(np.percentile(diff, 99)),
                                "diff_max_mm": float(diff.max()),
                                "same_pixels": bool(np.array_equal(sel, np.isfinite(new)))}
        doc["runs"].append(row)
        ref = row.get("reference")
        print(f"{scene:8s} {row['size'][1]}x{row['size'][0]} {row['pixels']} px: MAE {row['before']['mae']:.3f} -> "
              f"{row['refined']['mae']:.3f} mm in {new_s:.2f} s" + (f", peak {row['peak_cuda_gb']:.2f} GiB" if cuda else "")
              + (f" | host reference MAE {ref['mae']:.3f} in {ref['refine_s']:.2f} s, |diff| p99 "
                 f"{ref['diff_p99_mm']:.4f} max {ref['diff_max_mm']:.3f} mm" if ref else ""), flush=True)
    out = Path(args.out or REPO / "bench" / "results" / f"refine-time-{args.rig}-{dev.type}")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(doc, indent=1, default=float))
    header = ["scene", "pixels", "MAE before", "MAE refined", "refine s"]
    if cuda:
        header.append("peak GiB")
    if args.reference:
        header += ["host MAE", "host s", "|diff| p99 mm"]
    rows = []
    for r in doc["runs"]:
        row = [r["scene"], r["pixels"], f"{r['before']['mae']:.3f}", f"{r['refined']['mae']:.3f}", f"{r['refine_s']:.2f}"]
        if cuda:
            row.append(f"{r['peak_cuda_gb']:.2f}")
        if args.reference:
            row += [f"{r['reference']['mae']:.3f}", f"{r['reference']['refine_s']:.2f}", f"{r['reference']['diff_p99_mm']:.4f}"]
        rows.append(row)
    print(f"\nrefine_depth, rig {args.rig}, {doc['device']}, refine_range {args.refine_range:g} mm, chunk {args.chunk}\n")
    print("\n".join(markdown_table(header, rows)))
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
