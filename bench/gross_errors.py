"""Where a preset's gross errors come from: each scene of the virtual scanner reconstructed, its extraction run again
stage by stage, and every pixel off by more than --gross mm (default 20) traced to the stage after which it first
carried its wrong depth, with its distance to a depth edge of the ground truth and what GC(7) has there.

    python -m bench.gross_errors --preset fast --rigs default,oblique                # every scene of two rigs
    python -m bench.gross_errors --preset fast --scenes spheres --set edge_band_radius=0 --json G.json
    python -m bench.gross_errors --designs D --frames design3 --scenes rods   # a designed set (bench.designed_patterns)

One row per scene: the gross pixels (behind / in front of the truth), the RMSE with and without them against
GC(7)'s, the stage that first gave them their depth, how many lie within 1 pixel of a farther (the pixel is a
foreground outline given the background's depth) or a nearer ground-truth surface, GC(7)'s right answers there (within
5 mm), and their confidence (10th / 50th / 90th percentiles). Diagnosis: the figures are for finding causes.
"""
from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from bench.accuracy_sweep import _scan, neural_frames, parse_overrides

SCENES = "spheres,torus,boxes,bunny,vase,steps,checker,rods"


def edge_distance(gt: np.ndarray, ref: np.ndarray, sign: int, reach: int = 3, jump_mm: float = 20.0) -> np.ndarray:
    """[H, W] int8: the distance (Chebyshev, pixels, up to `reach`; 99 beyond) from each pixel to one whose ground
    truth is farther (sign +1) or nearer (sign -1) than its own by more than jump_mm; ref [H, W] bool: the pixels
    with a ground truth."""
    g = np.where(ref, gt, np.nan)
    H, W = g.shape
    out = np.full(g.shape, 99, np.int8)
    pad = np.pad(g, reach, constant_values=np.nan)
    for r in range(reach, 0, -1):  # the nearest ring last, so that it wins
        for dy in range(-r, r + 1):
            for dx in range(-r, r + 1):
                if max(abs(dy), abs(dx)) != r:
                    continue
                other = pad[reach + dy : reach + dy + H, reach + dx : reach + dx + W]
                with np.errstate(invalid="ignore"):
                    out[sign * (other - g) > jump_mm] = r
    return out


def first_wrong(maps: dict, gt: np.ndarray, gross: np.ndarray, gross_mm: float) -> dict:
    """{stage: the gross pixels (of the final map) that first carry a wrong depth (off by > gross_mm) after it}, the
    stages in their order; maps: {stage: depth [H, W] after it}."""
    seen = np.zeros_like(gross)
    out = {}
    for name, m in maps.items():
        with np.errstate(invalid="ignore"):
            now = gross & np.isfinite(m) & (np.abs(m - gt) > gross_mm) & ~seen
        out[name] = int(now.sum())
        seen |= now
    return out


def stage_maps(trainer) -> tuple[dict, object]:
    """({stage: depth [H, W] after it}, the Extraction) of the trainer's extraction as its run made it (over the
    renderer's lit pixels)."""
    from slwarp.neural.extraction import extract_depth

    maps = {}

    def keep(name, state):
        if state.depth is not None:
            maps[name] = np.asarray(state.depth, np.float32).copy()

    return maps, extract_depth(trainer, trainer.renderer.valid_map.cpu().numpy(), on_stage=keep)


def scene_row(rig: str, scene: str, preset_name: str, overrides: dict, device: str, gross_mm: float,
              designs: str | None = None, frames: str = "random6") -> dict:
    """One scene's row (see the module docstring): the neural run on `frames` (random6, gray7 or design<K>: the rig's
    set in `designs`, a folder of <rig>/design<K>/patterns.yaml)."""
    from slwarp.decode import reconstruct_depth
    from slwarp.neural.config import preset
    from slwarp.neural.extraction.state import pixel_fates
    from slwarp.neural.reconstruct import reconstruct

    t0 = time.perf_counter()
    scan, axis = _scan(rig, scene, 0, designs=designs, device=device)
    cfg = preset(preset_name, device=device, **overrides)
    rec = reconstruct(scan.select(neural_frames({"frames": frames}, axis)), cfg, progress=False)
    maps, final = stage_maps(rec.trainer)
    gt = scan.gt_depth
    ref = scan.mask & np.isfinite(gt) & (gt > 0)
    err = final.depth - gt
    has = ref & np.isfinite(final.depth)
    with np.errstate(invalid="ignore"):
        gross = has & (np.abs(err) > gross_mm)
    gc7, _, _ = reconstruct_depth(scan, "gc-interp", frames=f"gray:{axis}:bit=0-6:noinv")
    e7 = gc7 - gt
    has7 = ref & np.isfinite(gc7)
    farther, nearer = edge_distance(gt, ref, +1), edge_distance(gt, ref, -1)
    names = pixel_fates()
    return {"rig": rig, "scene": scene, "pixels": int(has.sum()), "gross": int(gross.sum()),
            "behind": int((gross & (err > 0)).sum()), "in_front": int((gross & (err < 0)).sum()),
            "rmse": float(np.sqrt(np.mean(err[has] ** 2))),
            "rmse_without_gross": float(np.sqrt(np.sum(err[has & ~gross] ** 2) / max(int(has.sum()), 1))),
            "rmse_gc7": float(np.sqrt(np.mean(e7[has7] ** 2))),
            "run_rmse": float(rec.metrics["rmse"]),  # the run's own extraction: the same map on a CPU
            "first_wrong_after": first_wrong(maps, gt, gross, gross_mm),
            "fates": {names[i]: int(c) for i, c in zip(*np.unique(final.fate[gross], return_counts=True))},
            "farther_within_1": int((gross & (farther == 1)).sum()), "nearer_within_1": int((gross & (nearer == 1)).sum()),
            "gc7_right": int((gross & (np.abs(np.nan_to_num(e7, nan=np.inf)) < 5)).sum()),
            "confidence": (np.nanpercentile(final.confidence[gross], [10, 50, 90]).round(3).tolist()
                           if gross.any() else None),
            # the same percentiles over the pixels within 5 mm: how a confidence bar would split right from gross
            "confidence_right": np.nanpercentile(final.confidence[has & (np.abs(np.nan_to_num(err)) <= 5)],
                                                 [10, 50, 90]).round(3).tolist(),
            "wall_s": time.perf_counter() - t0}


def markdown(rows: list[dict]) -> str:
    head = ("| rig | scene | gross px | behind / in front | RMSE mm | without them | GC(7) RMSE | first wrong after | "
            "outline (farther GT within 1 px) / nearer GT within 1 px | GC(7) right there | confidence p10/p50/p90 | "
            "right pixels' confidence p10/p50/p90 |")
    lines = [head, "|" + "---|" * 12]
    for r in rows:
        first = ", ".join(f"{k} {v}" for k, v in r["first_wrong_after"].items() if v)
        conf = "/".join(f"{c:.2f}" for c in r["confidence"]) if r["confidence"] else "-"
        right = "/".join(f"{c:.2f}" for c in r.get("confidence_right") or []) or "-"
        lines.append(f"| {r['rig']} | {r['scene']} | {r['gross']} | {r['behind']} / {r['in_front']} | {r['rmse']:.3f} | "
                     f"{r['rmse_without_gross']:.3f} | {r['rmse_gc7']:.3f} | {first or '-'} | {r['farther_within_1']} / "
                     f"{r['nearer_within_1']} | {r['gc7_right']} | {conf} | {right} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default="fast")
    p.add_argument("--rigs", default="default")
    p.add_argument("--scenes", default=SCENES)
    p.add_argument("--set", default="", help="option overrides, e.g. 'edge_band_radius=0'")
    p.add_argument("--device", default=None, help="default: cuda when present, else cpu")
    p.add_argument("--gross", type=float, default=20.0, help="an error above this many mm is gross (default 20)")
    p.add_argument("--json", help="also write the rows to this JSON file")
    p.add_argument("--frames", default="random6", help="what the neural run trains on: random6, gray7 or design<K>")
    p.add_argument("--designs", default=None, help="with --frames design<K>: the folder of <rig>/design<K>/patterns.yaml")
    args = p.parse_args(argv)
    if args.frames.startswith("design") and not args.designs:
        raise SystemExit(f"--frames {args.frames} needs --designs (a folder of <rig>/design<K>/patterns.yaml)")
    import torch

    device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
    overrides = parse_overrides(args.set)
    rows = []
    for rig in args.rigs.split(","):
        for scene in args.scenes.split(","):
            rows.append(scene_row(rig, scene, args.preset, overrides, device, args.gross, args.designs, args.frames))
            print(f"{rig} {scene}: {rows[-1]['gross']} gross pixels ({rows[-1]['wall_s']:.0f} s)", file=sys.stderr)
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"command": "python -m bench.gross_errors " + " ".join(argv if argv is not None else sys.argv[1:]),
                       "preset": args.preset, "overrides": overrides, "gross_mm": args.gross, "rows": rows}, f, indent=1)
    print(markdown(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
