"""Were the pixels each extraction stage dropped wrong? A finished run's extraction replayed stage by stage from its
checkpoint, and each stage's dropped pixels scored by the depth they had before it against a reference depth map.

    python -m bench.stage_drops RUN --scan data/real/capture_0/scan --reference data/real/capture_0/reference.npz
    python -m bench.stage_drops RUN --scan data/twin/procam/capture_1/scan --reference gt --json D.json

RUN: the output folder of `slwarp reconstruct` (its config.yaml and train/checkpoint.pt; the checkpoint is copied,
the run is left as it was). --reference: `gt` (the scan's ground truth), or a real capture's reference.npz
(bench.real_captures: its full 40-image decode is the reference, and its GC(7) decode of the same images is compared
on the pixels the stages dropped). One row per stage that dropped pixels: how many, how many the reference has, the
share of those whose depth before the stage lay within --tol mm of it (a high share: the stage dropped right
depths), and GC(7)'s share within --tol there; then the pixels GC(7) has and the final map lacks, and the reverse.
With --support K, whether the final map's neighbours would vouch for the drops still without depth (a readmission
by neighbour support, tried on paper before it is built). Diagnosis: the figures are for finding causes
(docs/accuracy.md, sections 36 and 37).

    python -m bench.stage_drops RUN --scan SCAN --reference gt --support 6
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np


def stage_maps_of_run(run: Path, scan) -> dict:
    """{stage: depth [H, W] mm after it} of a finished run's extraction replayed from a copy of its checkpoint (no
    training step: the checkpoint holds the final iteration), with the frames and the depth range the run used (its
    checkpoint's identity)."""
    from bench.gross_errors import stage_maps
    from slwarp.neural.config import load_config
    from slwarp.neural.training.checkpoint import read_checkpoint
    from slwarp.neural.training.trainer import Trainer

    identity = read_checkpoint(run / "train" / "checkpoint.pt").get("identity") or {}
    if identity.get("frames"):
        scan = scan.select([name for name, _ in identity["frames"]])
    depth_range = tuple(identity["depth_range"]) if identity.get("depth_range") else None
    with tempfile.TemporaryDirectory() as tmp:
        shutil.copytree(run / "train", Path(tmp) / "train")
        trainer = Trainer(scan, load_config(run / "config.yaml"), out_dir=Path(tmp) / "train", resume=True,
                          depth_range=depth_range)
        trainer.train()
        return stage_maps(trainer)[0]


def drop_rows(maps: dict, reference: np.ndarray, other: np.ndarray | None, tol_mm: float) -> list[dict]:
    """One row per stage that left pixels without depth: stage, dropped, with_reference (those the reference has),
    right_share (of those, the share whose depth before the stage lay within tol_mm of the reference), other_right
    (the same share for `other`'s depths there, None without it). maps: {stage: depth [H, W]} in stage order."""
    rows, before = [], None
    has_ref = np.isfinite(reference)
    for name, depth in maps.items():
        if before is not None:
            drop = np.isfinite(before) & ~np.isfinite(depth)
            if drop.any():
                scored = drop & has_ref
                right = np.abs(before - reference)[scored] <= tol_mm
                row = {"stage": name, "dropped": int(drop.sum()), "with_reference": int(scored.sum()),
                       "right_share": float(right.mean()) if right.size else float("nan"), "other_right": None}
                if other is not None:
                    o = scored & np.isfinite(other)
                    row["other_right"] = float((np.abs(other - reference)[o] <= tol_mm).mean()) if o.any() else None
                rows.append(row)
        before = depth
    return rows


def support_rows(maps: dict, reference: np.ndarray, tol_mm: float, min_kept: int) -> list[dict]:
    """Would the final map's neighbours vouch for what a stage dropped? Per stage with drops still without depth at
    the end: lost (how many, the reference has them), supported (those with at least `min_kept` of their 8
    neighbours holding a depth in the final map and their own depth before the stage within tol_mm of those
    neighbours' median), right (of the supported, within tol_mm of the reference), their MAE and largest error (mm).
    A readmission by neighbour support gives back right depths only where `right` is near `supported`."""
    from slwarp.neural.depth_maps import neighbour_stack

    names = list(maps)
    final = maps[names[-1]]
    kept = np.isfinite(final)
    around = neighbour_stack(final)  # [8, H, W], NaN where a neighbour has no depth
    n_kept = np.isfinite(around).sum(0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN neighbourhoods: no median, no support
        median = np.nanmedian(around, 0)
    rows = []
    for before_name, name in zip(names, names[1:]):
        before = maps[before_name]
        lost = np.isfinite(before) & ~np.isfinite(maps[name]) & ~kept & np.isfinite(reference)
        if not lost.any():
            continue
        err = np.abs(before - reference)
        sup = lost & (n_kept >= min_kept) & (np.abs(before - median) <= tol_mm)
        rows.append({"stage": name, "lost": int(lost.sum()), "lost_right": int((lost & (err <= tol_mm)).sum()),
                     "supported": int(sup.sum()), "supported_right": int((sup & (err <= tol_mm)).sum()),
                     "supported_mae": float(err[sup].mean()) if sup.any() else None,
                     "supported_max": float(err[sup].max()) if sup.any() else None})
    return rows


def support_markdown(rows: list[dict], tol_mm: float, min_kept: int) -> str:
    lines = [f"| stage | lost at the end (the reference has) | of them right | with {min_kept}+ neighbours kept, "
             f"within {tol_mm:g} mm of their median | of those right | their MAE / largest error mm |",
             "|---|---:|---:|---:|---:|---|"]
    for r in rows:
        err = "-" if r["supported_mae"] is None else f"{r['supported_mae']:.2f} / {r['supported_max']:.1f}"
        lines.append(f"| {r['stage']} | {r['lost']} | {r['lost_right']} | {r['supported']} | {r['supported_right']} "
                     f"| {err} |")
    return "\n".join(lines)


def exchange(final: np.ndarray, other: np.ndarray, reference: np.ndarray, tol_mm: float) -> dict:
    """The pixels `other` has and `final` lacks (only_other, and the share of those the reference has within tol_mm
    of other's depth), and the reverse (only_final, its share within tol_mm of the reference)."""
    out = {}
    for key, a, b in (("only_other", other, final), ("only_final", final, other)):
        m = np.isfinite(a) & ~np.isfinite(b)
        scored = m & np.isfinite(reference)
        out[key] = int(m.sum())
        out[key + "_right_share"] = float((np.abs(a - reference)[scored] <= tol_mm).mean()) if scored.any() else None
    return out


def markdown(rows: list[dict], ex: dict | None, tol_mm: float) -> str:
    lines = [f"| stage | dropped | the reference has | their depth within {tol_mm:g} mm of it | GC(7) within "
             f"{tol_mm:g} mm there |", "|---|---:|---:|---:|---:|"]
    for r in rows:
        other = "-" if r["other_right"] is None else f"{r['other_right']:.0%}"
        lines.append(f"| {r['stage']} | {r['dropped']} | {r['with_reference']} | {r['right_share']:.0%} | {other} |")
    if ex:
        share = lambda v: "-" if v is None else f"{v:.0%}"
        lines += ["", f"GC(7) has and the map lacks {ex['only_other']} pixels ({share(ex['only_other_right_share'])} "
                  f"within {tol_mm:g} mm of the reference); the map has and GC(7) lacks {ex['only_final']} "
                  f"({share(ex['only_final_right_share'])})."]
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run", help="a finished `slwarp reconstruct` output folder")
    p.add_argument("--scan", required=True, help="the scan folder the run reconstructed")
    p.add_argument("--reference", default="gt", help="'gt' (the scan's ground truth) or a real capture's reference.npz")
    p.add_argument("--tol", type=float, default=2.0, help="a depth within this many mm of the reference is right")
    p.add_argument("--support", type=int, default=0, metavar="K",
                   help="also: of each stage's drops still without depth at the end, those that K or more of their 8 "
                        "neighbours would vouch for (kept in the final map, their median within --tol), and how "
                        "many of those are right (a readmission by neighbour support, tried on paper)")
    p.add_argument("--json", help="also write the rows to this JSON file")
    args = p.parse_args(argv)
    from slwarp.scans.scan import load_scan

    run = Path(args.run)
    if not (run / "train" / "checkpoint.pt").is_file() or not (run / "config.yaml").is_file():
        raise SystemExit(f"{run}: not a finished run (it needs config.yaml and train/checkpoint.pt)")
    scan = load_scan(args.scan)
    other = None
    if args.reference == "gt":
        if scan.gt_depth is None:
            raise SystemExit(f"{args.scan}: the scan has no ground truth; give --reference reference.npz")
        reference = np.asarray(scan.gt_depth, np.float32)
    else:
        if not Path(args.reference).is_file():
            raise SystemExit(f"{args.reference}: no such reference file (bench.real_captures prepare writes them)")
        ref = np.load(args.reference)
        reference, other = ref["full_decode"], ref["gc7"]
    maps = stage_maps_of_run(run, scan)
    rows = drop_rows(maps, reference, other, args.tol)
    ex = exchange(maps[list(maps)[-1]], other, reference, args.tol) if other is not None else None
    support = support_rows(maps, reference, args.tol, args.support) if args.support > 0 else None
    if args.json:
        Path(args.json).write_text(json.dumps({
            "command": "python -m bench.stage_drops " + " ".join(argv if argv is not None else sys.argv[1:]),
            "tol_mm": args.tol, "rows": rows, "exchange": ex, "support_min_kept": args.support or None,
            "support": support,
            "pixels_with_depth": {k: int(np.isfinite(v).sum()) for k, v in maps.items()}}, indent=1))
    print(markdown(rows, ex, args.tol))
    if support is not None:
        print("\n" + support_markdown(support, args.tol, args.support))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
