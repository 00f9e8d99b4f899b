"""The image model's floor: how well each variant of the rendering model pins depth, at the true depth.

The neural method fits depth by comparing the images I_i with a model of them, I'_i = a + b Q_i(x), Q_i the
pattern (blurred as the camera sees it) sampled where the surface point x projects into the projector. If the
model is biased, no training recipe can beat its bias. This script measures that floor with an "oracle
decoder": for a random sample of valid pixels, every pixel's depth is moved by the same offset delta from its
exact ground truth (delta on a grid of --step mm within +-range), the photometric L1 cost of the model is
summed over a (2 r + 1)^2 window (each pixel keeps its own true depth: no fronto-parallel assumption; r = 0:
the pixel alone), and the offset of least cost is that pixel's depth error. A trained field is smooth, so
its error is shared by neighbouring pixels much as the window's offset is. A perfect model with no
noise gives 0; the share of pixels whose error exceeds 1 mm says where the model cannot pin depth at all.

Variants of the model (columns of the JSON; rows of the tables):
    ab         "minmax": a = min_i I_i, b = max_i I_i - a (today); "ls": a, b solved per pixel and per depth in
               closed form, least squares of I_i = a + b Q_i over the frames (b >= 0, a small ridge toward
               the min/max values where the codes barely vary)
    blur       "sharp": no blur; "global": one Gaussian sigma (projector px) fitted to the images at the true
               depth (today's fit, made at the depth-search map); "depth": sigma per projector-depth bin,
               fitted the same way and interpolated in z_p; "true": the simulator's own defocus law
               (sigma0 + slope |z_p - focus| / focus; a reference, only right without camera blur)
    response   "raw": the images as they are; "fit": the images linearised by I ** gamma, gamma fitted at
               the true depth (1 for a linear camera)

    python bench/model_floor.py                                  # small + default rig, all scenes and cameras
    python bench/model_floor.py --rig small --scenes bunny,checker --cameras linear --pixels 300   # quick

Writes bench/results/model-floor-cpu.{json,md} (or --out) and prints the tables. CPU only, a few minutes.
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

from image_model import (PatternStack, fit_depth_sigma, fit_gamma, fit_sigma, model_residual,  # noqa: E402
                         projector_uv_z)
from study_common import DATE, gray_code_yardstick, markdown_table, simulate_study_scan  # noqa: E402

VARIANTS = [  # (name, ab, blur, response)
    ("minmax, sharp (paper)", "minmax", "sharp", "raw"),
    ("minmax, global blur (today)", "minmax", "global", "raw"),
    ("ls, global blur", "ls", "global", "raw"),
    ("minmax, depth blur", "minmax", "depth", "raw"),
    ("ls, depth blur", "ls", "depth", "raw"),
    ("ls, true defocus law", "ls", "true", "raw"),
    ("minmax, global blur, gamma fit", "minmax", "global", "fit"),
    ("ls, global blur, gamma fit", "ls", "global", "fit"),
    ("ls, depth blur, gamma fit", "ls", "depth", "fit"),
]


def study_scan(scan, options, n_pixels: int, radii: list[int], half_range: float, step: float, seed: int = 0) -> dict:
    """Oracle-decoder errors of every variant on one scan (see module docstring), for windows of each radius
    in `radii` (0: the pixel alone)."""
    radius = max(radii)
    cam, prj = scan.camera, scan.projector
    H, W = cam.height, cam.width
    images = scan.images.astype(np.float64)  # [N, H, W]
    lo = images.min(0)
    valid = scan.mask & np.isfinite(scan.gt_depth) & (images.max(0) - lo > 0.05)
    rng = np.random.default_rng(seed)
    cand = np.flatnonzero(valid.ravel())
    centres = rng.choice(cand, size=min(n_pixels, cand.size), replace=False)
    cy, cx = np.divmod(centres, W)
    offs = [(dy, dx) for dy in range(-radius, radius + 1) for dx in range(-radius, radius + 1)]
    win = np.full((len(centres), len(offs)), -1, np.int64)
    for j, (dy, dx) in enumerate(offs):
        y, x = cy + dy, cx + dx
        ok = (y >= 0) & (y < H) & (x >= 0) & (x < W)
        idx = np.where(ok, y.clip(0, H - 1) * W + x.clip(0, W - 1), 0)
        win[:, j] = np.where(ok & valid.ravel()[idx], idx, -1)
    pix, inv = np.unique(win[win >= 0], return_inverse=True)
    win_local = np.full_like(win, -1)
    win_local[win >= 0] = inv
    centre_local = np.searchsorted(pix, centres)
    rays = cam.pixel_to_ray(cam.pixel_grid()).reshape(-1, 3)[pix]
    gt = scan.gt_depth.reshape(-1)[pix].astype(np.float64)
    obs = images.reshape(len(images), -1)[:, pix].T  # [P, N]
    stack = PatternStack(scan.patterns)
    uv0, zp0 = projector_uv_z(rays, gt, prj)
    sim = options

    def true_sigma(zp):
        if not sim.defocus:
            return np.zeros_like(zp)
        return sim.defocus_sigma + sim.defocus_slope * np.abs(zp - sim.focus_dist) / sim.focus_dist

    # per variant: the images (raw or linearised), a0, b0 and the blur as a function of z_p, fitted at the truth
    prepared, fits = {}, {}
    gamma_cache = {}
    for name, ab, blur, resp in VARIANTS:
        img = obs
        gamma = 1.0
        if resp == "fit":
            key = (ab, blur)
            if key not in gamma_cache:
                s_guess = fit_sigma(stack, obs, uv0, ab, obs.min(1), obs.max(1) - obs.min(1))
                gamma_cache[key] = fit_gamma(obs, stack.sample(uv0, s_guess), ab)
            gamma = gamma_cache[key]
            img = obs**gamma
        a0 = img.min(1)
        b0 = img.max(1) - a0
        if blur == "sharp":
            sig_fn, desc = (lambda zp: np.zeros_like(zp)), 0.0
        elif blur == "global":
            s = fit_sigma(stack, img, uv0, ab, a0, b0)
            sig_fn, desc = (lambda zp, s=s: np.full_like(zp, s)), round(s, 3)
        elif blur == "depth":
            zc, sc = fit_depth_sigma(stack, img, uv0, zp0, ab, a0, b0)
            sig_fn = lambda zp, zc=zc, sc=sc: np.interp(zp, zc, sc)  # noqa: E731
            desc = {"z_p": [round(float(z), 1) for z in zc], "sigma": [round(float(s), 3) for s in sc]}
        else:
            sig_fn, desc = true_sigma, "simulator"
        prepared[name] = (ab, img, a0, b0, sig_fn(zp0))
        fits[name] = {"sigma": desc, "gamma": gamma}

    deltas = np.arange(-half_range, half_range + 1e-9, step)
    cost = {(n, r): np.empty((len(deltas), len(centres))) for n in prepared for r in radii}
    resid_gt = {}
    wmask = win_local >= 0
    wl = np.where(wmask, win_local, 0)
    in_radius = {r: np.array([max(abs(dy), abs(dx)) <= r for dy, dx in offs]) for r in radii}
    for h, dlt in enumerate(deltas):
        uv, _ = projector_uv_z(rays, gt + dlt, prj)
        for name, (ab, img, a0, b0, sig) in prepared.items():
            q = stack.sample(uv, sig)
            r = model_residual(img, q, ab, a0, b0)
            c = np.abs(r).mean(-1) / np.maximum(b0, 1e-3)  # L1, relative to the pixel's modulation
            cw = c[wl] * wmask
            for rad in radii:
                cost[name, rad][h] = cw[:, in_radius[rad]].sum(1)
            if abs(dlt) < 1e-9:
                resid_gt[name] = float(np.mean(np.sqrt(np.mean(r**2, -1)) / np.maximum(b0, 1e-3)))

    def errors(cost):
        j = np.argmin(cost, 0)
        err = deltas[j].copy()
        inner = (j > 0) & (j < len(deltas) - 1)
        jj = np.clip(j, 1, len(deltas) - 2)
        c0, c1, c2 = (cost[jj - 1, np.arange(cost.shape[1])], cost[jj, np.arange(cost.shape[1])],
                      cost[jj + 1, np.arange(cost.shape[1])])
        den = c0 - 2 * c1 + c2
        refine = np.where(inner & (den > 0), 0.5 * step * (c0 - c2) / np.where(den > 0, den, 1.0), 0.0)
        e = np.abs(err + refine)
        return {"mae": float(e.mean()), "median": float(np.median(e)), "over_0.5mm": float((e > 0.5).mean()),
                "over_1mm": float((e > 1.0).mean())}

    out = {}
    for name in prepared:
        out[name] = {**{f"r{rad}": errors(cost[name, rad]) for rad in radii}, "residual_gt": resid_gt[name], **fits[name]}
    return {"variants": out, "pixels": int(len(centres)), "window_pixels": int(len(pix))}


def main(argv=None) -> int:
    from slwarp.sim.scenes import SCENE_NAMES
    from slwarp.sim.simulate import CAMERA_MODELS

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rigs", default="small,default")
    ap.add_argument("--scenes", default=",".join(SCENE_NAMES))
    ap.add_argument("--cameras", default=",".join(CAMERA_MODELS), help="camera models (slwarp.sim.simulate.CAMERA_MODELS)")
    ap.add_argument("--pixels", type=int, default=400, help="window centres per scan")
    ap.add_argument("--radii", default="0,3,5", help="window radii (px): (2r + 1)^2 pixels; 0 = the pixel alone")
    ap.add_argument("--range", type=float, default=3.0, dest="half_range", help="+- search range around the truth (mm)")
    ap.add_argument("--step", type=float, default=0.05, help="depth step of the search (mm; parabola refined)")
    ap.add_argument("--no-gray", action="store_true", help="skip the GC(6)/GC(7)-interp yardstick")
    ap.add_argument("--out", default=str(REPO / "bench" / "results" / "model-floor-cpu"))
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    doc = {"date": DATE, "machine": platform.processor() or platform.machine(), "args": vars(args), "runs": []}
    t_all = time.perf_counter()
    for rig in args.rigs.split(","):
        for camera in args.cameras.split(","):
            for scene in args.scenes.split(","):
                t0 = time.perf_counter()
                scan, options = simulate_study_scan(scene, rig, camera)
                radii = [int(r) for r in args.radii.split(",")]
                res = study_scan(scan.select("rand*"), options, args.pixels, radii, args.half_range, args.step)
                if not args.no_gray:
                    res["gray"] = gray_code_yardstick(scan)
                res.update(rig=rig, camera=camera, scene=scene, seconds=time.perf_counter() - t0)
                doc["runs"].append(res)
                write(doc, args.out, time.perf_counter() - t_all)  # after every scan: a long run keeps its rows
                v = res["variants"]
                print(f"{rig:8s} {camera:7s} {scene:8s} " + "  ".join(
                    f"{k.split(',')[0][:3]}/{k.split(',')[1].strip()[:6]}{'/g' if 'gamma' in k else ''} {v[k][f'r{max(radii)}']['mae']:.3f}"
                    for k in v) + f"  ({res['seconds']:.0f} s)", flush=True)
    print(write(doc, args.out, time.perf_counter() - t_all))
    return 0


def write(doc: dict, out: str, seconds: float) -> str:
    """Write <out>.json and <out>.md; returns the markdown."""
    doc["seconds"] = seconds
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(doc, indent=1, default=float))
    md = render_markdown(doc)
    out.with_suffix(".md").write_text(md)
    return md


def render_markdown(doc: dict) -> str:
    a = doc["args"]
    lines = [
        "# The image model's floor: oracle-decoder depth error per model variant",
        "",
        f"`python bench/model_floor.py --rigs {a['rigs']} --cameras {a['cameras']} --pixels {a['pixels']}` "
        f"({doc['date']}, CPU, {doc['seconds']:.0f} s). Per scan: {a['pixels']} random valid pixels (lit, contrast > "
        f"0.05); each pixel's depth moved by one offset from its exact ground truth within +-{a['half_range']} mm "
        f"(step {a['step']} mm, parabola-refined); the offset of least L1 photometric cost (relative to b) summed "
        "over a (2r+1)x(2r+1) window around the pixel (each pixel at its own true depth + the offset; r = 0: the "
        "pixel alone) is the error. Errors are capped by the range: '>1 mm' counts pixels the model cannot pin. "
        "Blur and gamma are fitted at the true depth. The 6 random patterns of the paper (pattern seed 0), noise "
        "seed 0. Gray code rows: all valid pixels of the same scan (its gray7 frames), for scale.",
        "",
    ]
    runs = doc["runs"]
    names = [v[0] for v in VARIANTS]
    for rig in dict.fromkeys(r["rig"] for r in runs):
        for camera in dict.fromkeys(r["camera"] for r in runs if r["rig"] == rig):
            sel = [r for r in runs if r["rig"] == rig and r["camera"] == camera]
            scenes = [r["scene"] for r in sel]
            radii = [int(x) for x in a["radii"].split(",")]
            tables = [(f"r{r}", "mae", "{:.3f}", f"oracle MAE mm, {'single pixel' if r == 0 else f'{2 * r + 1}x{2 * r + 1} window'}")
                      for r in sorted(radii, reverse=True)]
            tables.append((f"r{max(radii)}", "over_1mm", "{:.1%}", f"share of pixels off by > 1 mm, {2 * max(radii) + 1}x{2 * max(radii) + 1} window"))
            for kind, key, fmt, title in tables:
                rows = []
                for n in names:
                    vals = [r["variants"][n][kind][key] for r in sel]
                    rows.append([n] + [fmt.format(x) for x in vals] + [fmt.format(float(np.mean(vals)))])
                if key == "mae" and kind == f"r{max(radii)}" and "gray" in sel[0]:
                    for g in ("GC(7) interp", "GC(6) interp"):
                        vals = [r["gray"][g]["mae"] for r in sel]
                        rows.append([f"*{g} (all pixels, yardstick)*"] + [f"{x:.3f}" for x in vals] + [f"{np.mean(vals):.3f}"])
                lines += [f"## {rig} rig, camera model `{camera}`: {title}", ""]
                lines += markdown_table(["variant"] + scenes + ["mean"], rows) + [""]
            rows = []
            for n in names:
                vals = [r["variants"][n]["residual_gt"] for r in sel]
                rows.append([n] + [f"{x:.3f}" for x in vals] + [f"{np.mean(vals):.3f}"])
            lines += [f"## {rig} rig, camera model `{camera}`: RMS residual at the true depth, relative to b", ""]
            lines += markdown_table(["variant"] + scenes + ["mean"], rows) + [""]
            fit_rows = []
            for r in sel:
                v = r["variants"]
                fit_rows.append([r["scene"], f"{v['minmax, global blur (today)']['sigma']}", f"{v['ls, global blur']['sigma']}",
                                 json.dumps(v["ls, depth blur"]["sigma"]["sigma"]), f"{v['ls, depth blur, gamma fit']['gamma']}"])
            lines += [f"## {rig} rig, camera model `{camera}`: fitted blur (projector px) and gamma", ""]
            lines += markdown_table(["scene", "global sigma (minmax)", "global sigma (ls)", "depth-bin sigmas (ls, near to far)",
                                     "gamma (ls, depth blur)"], fit_rows) + [""]
    return "\n".join(lines)


if __name__ == "__main__":
    raise SystemExit(main())
