"""The search repair's growth (`slwarp.neural.search.grow_repair`) on depth maps the accuracy sweep kept, per scan
and neighbour support: pixels grown, grown right (within 3 mm) and wrong (over 20 mm), MAE before and after.

Why offline: the growth is the extraction's last step and reads nothing of the field, only the final depth map,
the pixels the repair changed and the scan's images, so a sweep's kept maps (`bench/accuracy_sweep.py --keep DIR`:
<run>.npz with the signed error and the pixel fates) can be grown again here, on the CPU, without the device that
trained them. The scan is simulated again (the sweep's own, `accuracy_sweep._scan`); the patterns are blurred by the
blur fitted at the true depth (the trainer fits it at the depth search's; both about 0.9 projector px here).

    python bench/grow_study.py --keep DIR                          # every neural run in DIR, supports 1, 2, 3
    python bench/grow_study.py --keep DIR --runs 'tuned__vertical__rods*' --supports 3

Writes <out>/grow-study.{json,md} (default bench/results).
"""
from __future__ import annotations

import argparse
import fnmatch
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "bench"))

from study_common import DATE, markdown_table, write_study  # noqa: E402

RIGHT_MM = 3.0  # a grown pixel within this of the truth is right
WRONG_MM = 20.0  # and one farther than this is on the wrong surface


def parse_run(path: Path) -> dict:
    """<label>__<rig>__<scene>__s<seed>__<method>.npz (accuracy_sweep.keep_error_map) -> its parts."""
    parts = path.stem.split("__")
    if len(parts) != 5 or not parts[3].startswith("s"):
        raise SystemExit(f"{path}: not a kept run of bench/accuracy_sweep.py "
                         "(<label>__<rig>__<scene>__s<seed>__<method>.npz)")
    return {"label": parts[0], "rig": parts[1], "scene": parts[2], "seed": int(parts[3][1:]), "method": parts[4]}


def grow_run(path: Path, supports: list[int], margin: float) -> dict:
    """The growth on one kept run, per support: counts and MAE before / after (over the pixels with depth)."""
    import torch

    from accuracy_sweep import _scan
    from slwarp.neural.pattern_model import blur_patterns, estimate_pattern_blur
    from slwarp.neural.extraction import FATE, PIXEL_FATES
    from slwarp.neural.extraction.repair import grow_repair
    from slwarp.neural.extraction.state import ModelInputs

    run = parse_run(path)
    kept = np.load(path)
    if "fate" not in kept:
        raise SystemExit(f"{path}: no pixel fates (a classical run, or kept before fates were saved)")
    if tuple(str(f) for f in kept["fates"]) != PIXEL_FATES:
        raise SystemExit(f"{path}: its fate names {list(kept['fates'])} are not this version's "
                         f"{list(PIXEL_FATES)}")
    scan, _ = _scan(run["rig"], run["scene"], run["seed"])
    rand = scan.select("rand*")
    error = kept["error"].astype(np.float32)
    if error.shape != scan.gt_depth.shape:
        raise SystemExit(f"{path}: a {error.shape} map for a {scan.gt_depth.shape} scan")
    gt = scan.gt_depth.astype(np.float32)
    depth = np.where(np.isfinite(error), gt + error, np.nan).astype(np.float32)
    images = np.asarray(rand.images, np.float32)
    patterns = np.asarray(rand.patterns, np.float32)
    sigma, _ = estimate_pattern_blur(rand.camera, rand.projector, images, patterns, np.where(scan.mask, gt, np.nan))
    rendered = blur_patterns(torch.as_tensor(patterns), sigma).numpy()
    seeds = kept["fate"] == FATE["repaired"]
    has = np.isfinite(depth)
    out = {**run, "blur_px": float(sigma), "seeds": int(seeds.sum()), "pixels": int(has.sum()),
           "mae_before": float(np.abs(error[has]).mean()), "wrong_before": int((np.abs(error[has]) > WRONG_MM).sum()),
           "supports": {}}
    inputs = ModelInputs(rand.camera, rand.projector, images, rendered, scan.depth_range)
    for support in supports:
        t0 = time.perf_counter()
        new, grown = grow_repair(depth, seeds, inputs, support=support, margin=margin)
        e = new - gt
        out["supports"][str(support)] = {
            "grown": int(grown.sum()), "right": int((grown & (np.abs(e) < RIGHT_MM)).sum()),
            "wrong": int((grown & (np.abs(e) > WRONG_MM)).sum()), "mae_after": float(np.abs(e[has]).mean()),
            "wrong_after": int((np.abs(e[has]) > WRONG_MM).sum()), "seconds": time.perf_counter() - t0}
    return out


def render(doc: dict) -> str:
    lines = [f"# The search repair's growth on kept depth maps (CPU, {doc['date']})", "",
             f"`{doc['command']}`. Each run's final depth map (kept by `bench/accuracy_sweep.py --keep`) grown again "
             "with `search.grow_repair` from the pixels the repair changed (seeds); right: a grown pixel within "
             f"{RIGHT_MM:g} mm of the truth, wrong: over {WRONG_MM:g} mm; 'off > 20 mm' counts the map's pixels "
             f"that far off; margin {doc['margin']}." + (f" {doc['note']}" if doc.get("note") else ""), ""]
    header = ["run", "seeds", "MAE before mm", "off > 20 mm before"]
    for s in doc["supports"]:
        header += [f"support {s}: grown / right / wrong", f"support {s}: MAE after", f"support {s}: off > 20 mm"]
    rows = []
    for r in doc["runs"]:
        row = [f"{r['label']} {r['rig']} {r['scene']}", r["seeds"], f"{r['mae_before']:.3f}", r["wrong_before"]]
        for s in doc["supports"]:
            g = r["supports"][str(s)]
            row += [f"{g['grown']} / {g['right']} / {g['wrong']}", f"{g['mae_after']:.3f}", g["wrong_after"]]
        rows.append(row)
    return "\n".join(lines + markdown_table(header, rows)) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--keep", required=True, help="the folder of bench/accuracy_sweep.py --keep")
    ap.add_argument("--runs", default="*", help="glob over the kept runs' names (default: every neural run)")
    ap.add_argument("--supports", default="1,2,3", help="comma-separated neighbour supports to try")
    ap.add_argument("--margin", type=float, default=0.0, help="confidence margin of a switch (grow_repair's)")
    ap.add_argument("--note", default=None, help="a sentence for the header (where the kept maps came from)")
    ap.add_argument("--out", default=str(REPO / "bench" / "results"))
    args = ap.parse_args(argv)
    keep = Path(args.keep)
    if not keep.is_dir():
        raise SystemExit(f"--keep {keep}: no such folder")
    paths = sorted(p for p in keep.glob("*__*__*__s*__*.npz")
                   if fnmatch.fnmatch(p.stem, args.runs) and not p.stem.startswith("classical__"))
    if not paths:
        raise SystemExit(f"--keep {keep}: no neural run matches {args.runs!r}")
    supports = [int(s) for s in args.supports.split(",")]
    given = argv if argv is not None else sys.argv[1:]
    shown = [a for i, a in enumerate(given) if a != "--note" and (i == 0 or given[i - 1] != "--note")]
    doc = {"date": DATE, "command": "python bench/grow_study.py " + " ".join(shown),
           "margin": args.margin, "supports": supports, "note": args.note, "runs": []}
    for i, p in enumerate(paths, 1):
        t0 = time.perf_counter()
        doc["runs"].append(grow_run(p, supports, args.margin))
        print(f"[{i}/{len(paths)}] {p.stem} ({time.perf_counter() - t0:.0f} s)", flush=True)
    write_study(Path(args.out) / "grow-study", doc, render)
    return 0


if __name__ == "__main__":
    sys.exit(main())
