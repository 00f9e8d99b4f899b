"""Time of the photometric residual (`slwarp.neural.pattern_model.photometric_residual`), of the repair's growth
(`slwarp.neural.extraction.repair.grow_repair`) and of the depth grouping (`slwarp.neural.search.component_sizes`) on one
simulated scan. The residual per share of pixels with depth and per way of computing it:

- "dense, ray grid per call": every pixel, the camera's ray grid undistorted again each call (as before it was
  cached per camera: `decode.triangulate.camera_rays`);
- "dense": every pixel, the ray grid cached;
- "sparse": at the pixels with depth only (what the residual does below pattern_model.SPARSE_SHARE).

Each row checks that its values equal the dense ones. The growth runs on the scan's true depth with a 32 x 80 px
patch pushed 40 mm back inside a block of "repaired" pixels, with its confidences sparse (as in the extraction) and
dense. The grouping runs on the scan's true depth with a fifth of its pixels dropped at random (the groups are
checked by their total: every finite pixel in exactly one group), and so does the depth search's 3x3 outlier
median (`search._median3`), checked equal to np.nanmedian's, which it replaced.

    python bench/residual_speed.py                  # default rig (1280 x 1024), rods
    python bench/residual_speed.py --rig small --scene bunny --out /tmp/rs

Writes <out>/residual-speed-<device>.{json,md} (default bench/results). Times are the median of --repeat runs.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "bench"))

from study_common import DATE, markdown_table, write_study  # noqa: E402

SHARES = (0.002, 0.02, 0.2, 1.0)


def _median_time(fn, repeat: int) -> tuple[float, object]:
    times, out = [], None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times), out


def median3_nanmedian(x: np.ndarray) -> np.ndarray:
    """The 3x3 outlier median as np.nanmedian takes it (the reference for search._median3)."""
    import warnings

    from slwarp.neural.extraction.surface import neighbour_stack

    stack = np.concatenate([neighbour_stack(x), x[None]]).astype(x.dtype)  # [9, H, W]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        med = np.nanmedian(stack, axis=0)
    with np.errstate(invalid="ignore"):
        return np.where(np.abs(x - med) < 10.0, x, np.nan)


def measure(rig: str, scene: str, repeat: int) -> dict:
    import torch

    import importlib

    from slwarp.neural import pattern_model as pm
    from slwarp.neural.extraction.repair import grow_repair
    from slwarp.neural.extraction.state import ModelInputs
    from slwarp.neural.search import AGREE_MM, _median3, component_sizes
    from slwarp.sim.simulate import SimOptions, simulate_scene

    scan = simulate_scene(scene, "random6", rig=rig, options=SimOptions(seed=0), device="cpu")
    images = scan.images[:6]
    patterns = pm.blur_patterns(torch.as_tensor(scan.patterns[:6]), 1.0).numpy()
    cam, prj = scan.camera, scan.projector
    rng = np.random.default_rng(0)
    sparse_share = pm.SPARSE_SHARE
    rays_cache = importlib.import_module("slwarp.decode.triangulate")._RAYS_CACHE

    def residual(depth, share, cached=True):
        pm.SPARSE_SHARE = share
        try:
            if not cached:
                rays_cache.clear()
            return pm.photometric_residual(depth, cam, prj, images, patterns)
        finally:
            pm.SPARSE_SHARE = sparse_share

    rows = []
    residual(scan.gt_depth, 0.0)  # the ray grid cached once, outside the timings
    for share in SHARES:
        depth = np.where(rng.random(scan.gt_depth.shape) < share, scan.gt_depth, np.nan).astype(np.float32)
        t_dense, dense = _median_time(lambda: residual(depth, 0.0), repeat)
        t_uncached, uncached = _median_time(lambda: residual(depth, 0.0, cached=False), repeat)
        row = {"share": share, "pixels": int(np.isfinite(depth).sum()), "dense_ray_grid_per_call_s": t_uncached,
               "dense_s": t_dense, "same": bool(np.array_equal(uncached, dense, equal_nan=True))}
        if share < 1.0:
            t_sparse, sparse = _median_time(lambda: residual(depth, 1.0), repeat)
            row.update(sparse_s=t_sparse, same=row["same"] and bool(np.array_equal(sparse, dense, equal_nan=True)))
        rows.append(row)

    # the growth: a patch 40 mm behind its surface in a block of repaired pixels, on the scan's true depth
    valid = np.isfinite(scan.gt_depth) & scan.mask
    H, W = valid.shape
    bh, bw = H // 8, W // 8
    y0, x0 = next((y, x) for y in range(0, H - bh, bh // 4) for x in range(0, W - bw, bw // 4)
                  if valid[y : y + bh, x : x + bw].all())
    seeds = np.zeros_like(valid)
    seeds[y0 : y0 + bh, x0 : x0 + bw] = True
    wrong = np.zeros_like(valid)
    wrong[y0 + bh // 6 : y0 + bh - bh // 6, x0 + bw - bw // 4 : x0 + bw - 4] = True
    seeds &= ~wrong
    depth = np.where(valid, scan.gt_depth, np.nan).astype(np.float32)
    depth[wrong] += 40.0

    inputs = ModelInputs(cam, prj, images, patterns, scan.depth_range)

    def grow(share):
        pm.SPARSE_SHARE = share
        try:
            return grow_repair(depth, seeds, inputs)
        finally:
            pm.SPARSE_SHARE = sparse_share

    t_sparse, (out_s, grown_s) = _median_time(lambda: grow(sparse_share), repeat)
    t_dense, (out_d, grown_d) = _median_time(lambda: grow(0.0), repeat)
    growth = {"patch_pixels": int(wrong.sum()), "grown": int(grown_s.sum()), "sparse_s": t_sparse, "dense_s": t_dense,
              "same": bool(np.array_equal(out_s, out_d, equal_nan=True) and np.array_equal(grown_s, grown_d))}
    # the grouping and the outlier median: the true depth with a fifth of the pixels dropped
    holes = np.where(rng.random(depth.shape) < 0.2, np.nan, scan.gt_depth).astype(np.float32)
    component_sizes(holes[:8, :8], AGREE_MM)  # imports outside the timing
    t_groups, sizes = _median_time(lambda: component_sizes(holes, AGREE_MM), repeat)
    finite = np.isfinite(holes)
    n_groups = float((1.0 / sizes[finite]).sum())  # each group's pixels add up to 1
    grouping = {"pixels": int(finite.sum()), "groups": int(round(n_groups)), "s": t_groups,
                "same": bool(abs(n_groups - round(n_groups)) < 1e-6 and (sizes[~finite] == 0).all())}
    t_sorted, kept = _median_time(lambda: _median3(holes), repeat)
    t_nan, kept_ref = _median_time(lambda: median3_nanmedian(holes), repeat)
    median3 = {"sorted_s": t_sorted, "nanmedian_s": t_nan, "same": bool(np.array_equal(kept, kept_ref, equal_nan=True))}
    return {"rig": rig, "scene": scene, "camera": f"{cam.width}x{cam.height}", "frames": len(images),
            "repeat": repeat, "residual": rows, "growth": growth, "grouping": grouping,
            "median3": median3}


def render(doc: dict) -> str:
    lines = [f"# Photometric residual, the repair's growth, the depth grouping and the outlier median: time per call ({doc['device']}, {doc['date']})", "",
             f"`{doc['command']}`: {doc['scene']} on the {doc['rig']} rig ({doc['camera']} px, {doc['frames']} "
             f"frames), median of {doc['repeat']} runs; 'same' checks every row's values against the dense ones.", ""]
    header = ["share of pixels with depth", "pixels", "dense, ray grid per call s", "dense s", "sparse s", "same"]
    rows = [[f"{r['share']:.1%}", r["pixels"], f"{r['dense_ray_grid_per_call_s']:.3f}", f"{r['dense_s']:.3f}",
             f"{r['sparse_s']:.3f}" if "sparse_s" in r else "-", "yes" if r["same"] else "NO"] for r in doc["residual"]]
    lines += markdown_table(header, rows) + [""]
    g = doc["growth"]
    lines += [f"The repair's growth (a {g['patch_pixels']}-pixel patch 40 mm back inside repaired pixels; "
              f"{g['grown']} grown):", ""]
    lines += markdown_table(["confidences", "s"], [["at the candidates (sparse)", f"{g['sparse_s']:.3f}"],
                                                    ["over the whole map (dense)", f"{g['dense_s']:.3f}"]])
    lines += ["", f"Same result both ways: {'yes' if g['same'] else 'NO'}.", ""]
    c = doc.get("grouping")
    if c:
        lines += [f"The depth grouping (`component_sizes`, neighbours joined within search.AGREE_MM) of {c['pixels']} pixels with depth: "
                  f"{c['s']:.3f} s, {c['groups']} groups; sizes consistent: {'yes' if c['same'] else 'NO'}.", ""]
    m = doc.get("median3")
    if m:
        lines += [f"The depth search's 3x3 outlier median on the same map: {m['sorted_s']:.3f} s by one sort per pixel "
                  f"(`search._median3`), {m['nanmedian_s']:.3f} s by np.nanmedian; same result: "
                  f"{'yes' if m['same'] else 'NO'}.", ""]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rig", default="default")
    ap.add_argument("--scene", default="rods")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", default=str(REPO / "bench" / "results"))
    args = ap.parse_args(argv)
    doc = measure(args.rig, args.scene, args.repeat)
    doc.update(device="CPU", date=DATE, command=" ".join(
        ["python bench/residual_speed.py", *(argv if argv is not None else sys.argv[1:])]))
    write_study(Path(args.out) / "residual-speed-cpu", doc, render)
    checks = [r["same"] for r in doc["residual"]] + [doc[k]["same"] for k in ("growth", "grouping", "median3")]
    return 0 if all(checks) else 1


if __name__ == "__main__":
    sys.exit(main())
