"""Where a real capture's plate error lies: by spatial scale, and what the photometric refinement does to it.

For depth maps of a prepared real capture (bench.real_captures prepare: data/real/capture_N/), the chessboard plate's
points are fitted with a plane (as `bench.real_captures` reports its plate RMS) and the residual map is split by
scale: the RMS left after subtracting its box mean over (2s + 1)^2 pixels, for s = 2 ... 32 (pixel noise stays in
the small scales; a waviness over tens of pixels only in the large ones), and the spread of its mean per image row
and column (a bias that follows the projector's rows shows in the row means on this vertical-baseline rig). The full
40-image decode and GC(7)-interp of the same 7 images come first, as references.

`--refine-gains T1,T2,...`: the first map refined (`pattern_model.refine_depth`'s window search over +-3 mm), each
pixel's move kept only where its window's best cost is below (1 - T) x its cost at the map's own depth (T = 0: the
refinement as it is), then the presets' GPU denoising (radius 4, 8 footprints); the plate RMS, the same by scale
and the median agreement with the full decode. A gain test asks whether a window says more than its noise.

    python -m bench.plate_residuals --capture 2 RUN/capture_2/fast/depth.npy OTHER/depth.npy
    python -m bench.plate_residuals --capture 2 RUN/depth.npy --refine-gains 0,0.05,0.1 --stem plate-residuals-c2

CPU (the refinement of a 1280x1024 map takes about 2 minutes on 2 cores). Writes <out>/<stem>.json and .md.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

from bench import DATE, markdown_table, write_study

SCALES = (2, 4, 8, 16, 32)
DENOISE = dict(radius=4, footprints=8.0)  # the GPU presets' denoising window


def plate_residual(depth: np.ndarray, region: np.ndarray, camera) -> np.ndarray:
    """[H, W] signed distance (mm) of each plate pixel's point to the plane fitted to all of them; NaN elsewhere."""
    from slwarp.neural.depth_maps import depth_to_points

    d = np.where(region, depth, np.nan)
    ok = np.isfinite(d)
    out = np.full(d.shape, np.nan)
    if ok.sum() < 3:
        return out
    P = depth_to_points(d, camera).astype(np.float64)
    c = P.mean(0)
    normal = np.linalg.svd(P - c, full_matrices=False)[2][2]
    out[ok] = (P - c) @ normal
    return out


def by_scale(r: np.ndarray) -> dict:
    """The residual map's RMS, its RMS after each box mean's removal (hp<s>), and the spread of its row and column means."""
    import cv2

    ok = np.isfinite(r)
    if not ok.any():
        return {"rms": float("nan")}
    out = {"rms": float(np.sqrt(np.mean(r[ok] ** 2)))}
    values, weight = np.where(ok, r, 0.0), ok.astype(np.float64)
    for s in SCALES:
        k = (2 * s + 1, 2 * s + 1)
        mean = cv2.blur(values, k) / np.maximum(cv2.blur(weight, k), 1e-9)
        out[f"hp{s}"] = float(np.sqrt(np.mean((r - mean)[ok] ** 2)))
    rows, cols = np.nanmean(np.where(ok, r, np.nan)[ok.any(1)], 1), np.nanmean(np.where(ok, r, np.nan)[:, ok.any(0)], 0)
    out["row_mean_std"], out["col_mean_std"] = float(np.std(rows)), float(np.std(cols))
    return out


def refined_with_gain(depth: np.ndarray, scan, gains: list[float], half_range_mm: float = 3.0) -> dict:
    """{gain: depth map} for `depth` refined as pattern_model.refine_depth does (a window's common offset, L1 cost
    relative to b, least-squares a and b, the blur per projector depth), each move kept only where the window's best
    cost is below (1 - gain) x its cost at offset 0; and the share of moved pixels per gain."""
    import torch

    from slwarp.neural.pattern_model import refine as R
    from slwarp.neural.pattern_model.blur import _interp, _projector_uv
    from slwarp.neural.pattern_model.image import MIN_MODULATION, least_squares_residual

    m = R._fit_model(depth, scan.camera, scan.projector, scan.images, scan.patterns, "cpu")
    d, ok, img, b, rays, ladder = m.d, m.has, m.img, m.b, m.rays, m.ladder
    zp = rays.ray[..., 2] * d.double() + rays.T[2]
    pos = ladder.position(_interp(torch.nan_to_num(zp, nan=0.0).where(ok, m.centres[0]), m.centres, m.sigmas).float())
    deltas = np.arange(-half_range_mm, half_range_mm + 1e-9, R.REFINE_STEP_MM)
    k, radius = 2 * R.REFINE_RADIUS + 1, R.REFINE_RADIUS
    inv_b = torch.where(ok, 1.0 / b.clamp_min(MIN_MODULATION), torch.zeros_like(b))
    d0 = torch.where(ok, d, torch.zeros_like(d))
    best = torch.full(depth.shape, float("inf"))
    best_j = torch.zeros(depth.shape, dtype=torch.int64)
    zero = int(np.argmin(np.abs(deltas)))
    at_zero = None
    for j0 in range(0, len(deltas), 8):
        dl = torch.as_tensor(deltas[j0:j0 + 8].astype(np.float32))
        uv = _projector_uv(rays.ray32 * (d0[None] + dl[:, None, None])[..., None] + rays.T32, m.projector)
        r = least_squares_residual(img[:, None], ladder.sample(uv, pos.expand(dl.numel(), *depth.shape)), b[None])
        cost = torch.nn.functional.avg_pool2d((r.abs().mean(0) * inv_b)[:, None], k, stride=1, padding=radius,
                                              count_include_pad=True)[:, 0] * float(k * k)
        if j0 <= zero < j0 + dl.numel():
            at_zero = cost[zero - j0].clone()
        cmin, cidx = cost.min(0)
        better = cmin < best
        best, best_j = torch.where(better, cmin, best), torch.where(better, cidx + j0, best_j)
    offset = torch.as_tensor(deltas)[best_j].numpy()
    okn, best, at_zero = ok.numpy(), best.numpy(), at_zero.numpy()
    out, moved = {}, {}
    for g in gains:
        keep = okn & (best < (1.0 - g) * at_zero)
        out[g] = np.where(keep, depth + offset, depth).astype(np.float32)
        moved[g] = float(keep[okn].mean())
    return out, moved


def render(doc: dict) -> str:
    lines = [f"# The plate's error by scale, capture {doc['capture']} (CPU, {doc['date']})", "",
             f"`{doc['command']}`", "",
             "Residual to the plate's fitted plane (mm): its RMS (the plate RMS of bench.real_captures), the RMS left "
             "after removing its mean over (2s + 1)^2 pixels (hp<s>: what varies within s pixels), and the spread of its "
             "mean per image row and per column. The calibration bends the plate by about 0.4 mm RMS for every method "
             "(a large-scale part).", ""]
    head = ["map", "plate RMS"] + [f"hp{s}" for s in SCALES] + ["row means", "column means", "agreement median"]
    rows = [[r["name"], f"{r['rms']:.3f}"] + [f"{r[f'hp{s}']:.3f}" for s in SCALES]
            + [f"{r['row_mean_std']:.3f}", f"{r['col_mean_std']:.3f}",
               "-" if r.get("agree_median_mm") is None else f"{r['agree_median_mm']:.3f}"] for r in doc["maps"]]
    lines += markdown_table(head, rows) + [""]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("depths", nargs="+", help="depth maps (.npy, mm, NaN: none) of the capture")
    ap.add_argument("--capture", type=int, required=True)
    ap.add_argument("--data", default=str(REPO / "data" / "real"))
    ap.add_argument("--refine-gains", default=None, help="comma-separated gain thresholds for the first map")
    ap.add_argument("--out", default=str(REPO / "bench" / "results"))
    ap.add_argument("--stem", default="plate-residuals")
    args = ap.parse_args(argv)
    from slwarp.neural.extraction.surface import denoise_depth
    from slwarp.scans.scan import load_scan

    folder = Path(args.data) / f"capture_{args.capture}"
    if not (folder / "reference.npz").is_file():
        raise SystemExit(f"{folder}: no prepared capture (python -m bench.real_captures prepare)")
    for p in args.depths:
        if not Path(p).is_file():
            raise SystemExit(f"{p}: no such depth map")
    scan = load_scan(folder / "scan")
    ref = dict(np.load(folder / "reference.npz"))
    region, full = ref["region"], ref["full_decode"]

    def row(name: str, depth: np.ndarray, **extra) -> dict:
        if depth.shape != region.shape:
            raise SystemExit(f"{name}: a {depth.shape} map, the capture's images are {region.shape}")
        both = np.isfinite(depth) & np.isfinite(full)
        agree = float(np.median(np.abs(depth[both] - full[both]))) if both.any() else None
        r = {"name": name, **by_scale(plate_residual(depth, region, scan.camera)), "agree_median_mm": agree, **extra}
        print(f"{name}: plate RMS {r['rms']:.3f} mm", flush=True)
        return r

    maps = [row("full 40-image decode", full), row("GC(7)-interp, same 7 images", ref["gc7"])]
    maps += [row(p, np.load(p)) for p in args.depths]
    if args.refine_gains:
        gains = [float(g) for g in args.refine_gains.split(",")]
        first = np.load(args.depths[0])
        refined, moved = refined_with_gain(first, scan, gains)
        for g in gains:
            denoised = denoise_depth(refined[g], scan.camera, DENOISE["radius"], DENOISE["footprints"])
            maps.append(row(f"first refined, gain >= {g:g} ({moved[g]:.0%} moved), denoised", denoised,
                            gain=g, moved=moved[g]))
    doc = {"date": DATE, "command": "python -m bench.plate_residuals " + " ".join(sys.argv[1:] if argv is None else argv),
           "capture": args.capture, "maps": maps}
    write_study(Path(args.out) / args.stem, doc, render)
    return 0


if __name__ == "__main__":
    sys.exit(main())
