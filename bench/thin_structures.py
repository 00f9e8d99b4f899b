"""Thin structures (the `rods` scene: 2.5 mm rods, about 2 px wide on the small rig): where the neural method
loses them, and what a per-pixel fallback to a depth search recovers.

1. The depth search that starts training: the share of rod pixels (and of all pixels) whose search depth is
   within 5 mm of the truth, for the library's search (slwarp.neural.search.search_depth: 5x5 window, stride,
   confidence test, 3x3 median outlier removal) and for plain cost-volume searches without the confidence and
   median steps: the 5x5 square window, and adaptive windows (the square or a 7-pixel line in one of 4
   directions, whichever has the least mean cost).
2. The trained field (preset `cpu`, cached with the other study scripts), and per pixel the trained depth or a
   search depth, whichever explains the pixel's own images better (least-squares model, blur per
   projector-depth bin; switched only where they differ by > 5 mm and the search's cost is < 0.7x), each
   through the flying-pixel and photometric filters and the photometric refinement (image_model.refine_depth).

    python bench/thin_structures.py               # rods and bunny (a scene without thin parts, for regressions)

Writes bench/results/thin-structures-cpu.{json,md}.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "bench"))

from image_model import PatternStack, fit_model, model_residual, projector_uv_z, refine_depth  # noqa: E402
from study_common import (DATE, gray_code_yardstick, markdown_table, simulate_study_scan,  # noqa: E402
                          train_cached, write_study)

ROD_DEPTH_MM = 685.0  # every rod of the scene lies nearer than this, every other surface farther
SQUARE = [(dy, dx) for dy in range(-2, 3) for dx in range(-2, 3)]
LINES = [[(0, d) for d in range(-3, 4)], [(d, 0) for d in range(-3, 4)], [(d, d) for d in range(-3, 4)],
         [(d, -d) for d in range(-3, 4)]]


def cost_volume(scan, step: float = 2.0, sigma: float = 1.0):
    """(depths [D], per-pixel L1 cost [D, H, W] of a + b P (min/max a, b; patterns blurred by sigma px))."""
    cam, prj = scan.camera, scan.projector
    im = scan.images.astype(np.float64)
    a = im.min(0).reshape(-1, 1)
    b = (im.max(0) - im.min(0)).reshape(-1, 1)
    zs = np.arange(scan.depth_range[0] + step / 2, scan.depth_range[1], step)
    rays = cam.pixel_to_ray(cam.pixel_grid()).reshape(-1, 3)
    obs = im.reshape(len(im), -1).T
    stack = PatternStack(scan.patterns)
    C = np.empty((len(zs), cam.height * cam.width), np.float32)
    for h, z in enumerate(zs):
        uv, _ = projector_uv_z(rays, np.full(len(rays), z), prj)
        C[h] = np.abs(a + b * stack.sample(uv, sigma) - obs).mean(1)
    return zs, C.reshape(len(zs), cam.height, cam.width)


def window_mean(C: np.ndarray, valid: np.ndarray, offsets) -> np.ndarray:
    """Mean of C [D, H, W] over the valid pixels at the given (dy, dx) offsets of each pixel."""
    _, H, W = C.shape
    num = np.zeros_like(C)
    den = np.zeros((H, W), np.float32)
    Cv = np.where(valid[None], C, 0.0)
    for dy, dx in offsets:
        ys, yd = slice(max(dy, 0), H + min(dy, 0)), slice(max(-dy, 0), H + min(-dy, 0))
        xs, xd = slice(max(dx, 0), W + min(dx, 0)), slice(max(-dx, 0), W + min(-dx, 0))
        num[:, yd, xd] += Cv[:, ys, xs]
        den[yd, xd] += valid[ys, xs]
    return num / np.maximum(den, 1)[None]


def pixel_cost(scan, depth: np.ndarray, sigma_fn) -> np.ndarray:
    """[H, W] relative RMS residual of the least-squares model at each pixel's depth (inf where NaN)."""
    ok = np.isfinite(depth)
    out = np.full(depth.shape, np.inf)
    obs = scan.images[:, ok].T.astype(np.float64)
    a0 = obs.min(1)
    b0 = obs.max(1) - a0
    uv, zp = projector_uv_z(scan.camera.pixel_to_ray(scan.camera.pixel_grid())[ok], depth[ok].astype(np.float64), scan.projector)
    r = model_residual(obs, PatternStack(scan.patterns).sample(uv, sigma_fn(zp)), "ls", a0, b0)
    out[ok] = np.sqrt(np.mean(r**2, 1)) / np.maximum(b0, 1e-3)
    return out


def main(argv=None) -> int:
    from slwarp.evaluation.metrics import depth_metrics
    from slwarp.neural.extraction.surface import extract_mesh, flying_pixel_filter, mesh_depth
    from slwarp.neural.pattern_model import photometric_filter
    from slwarp.neural.pattern_model import blur_patterns
    from slwarp.neural.search import search_depth

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", default="rods,bunny")
    ap.add_argument("--preset", default="cpu")
    ap.add_argument("--cache", default="/tmp/slwarp-study-fields")
    ap.add_argument("--out", default=str(REPO / "bench" / "results" / "thin-structures-cpu"))
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    doc = {"date": DATE, "args": vars(args), "runs": []}
    for scene in args.scenes.split(","):
        t0 = time.perf_counter()
        full, _ = simulate_study_scan(scene, "small", "linear")
        scan = full.select("rand*")
        gt = scan.gt_depth
        b = scan.images.max(0) - scan.images.min(0)
        valid = b > 0.05
        groups = {"all": scan.mask & valid}
        if scene == "rods":
            groups["rods"] = scan.mask & valid & (gt < ROD_DEPTH_MM)
        zs, C = cost_volume(scan)
        square = window_mean(C, valid, SQUARE)
        line = np.stack([window_mean(C, valid, o) for o in LINES]).min(0)
        library, _ = search_depth(scan.camera, scan.projector, scan.images,
                                  blur_patterns(torch.as_tensor(scan.patterns), 1.0).numpy(), scan.depth_range,
                                  valid=valid, step_mm=2.0, stride=1, device="cpu")
        searches = {"library search (stride 1)": library, "square 5x5, no confidence test": zs[square.argmin(0)],
                    "adaptive windows, no confidence test": zs[np.minimum(square, line).argmin(0)]}
        search_rows = {}
        for name, d in searches.items():
            e = np.abs(np.where(valid, d, np.nan) - gt)
            search_rows[name] = {g: {"within_5mm": float((e[s] < 5).mean()), "wrong_over_5mm": float((e[s] >= 5).mean()),
                                     "no_answer": float(np.isnan(e[s]).mean())} for g, s in groups.items()}
        trainer, cfg, _ = train_cached(scan, args.preset, "baseline", Path(args.cache), key=f"small-linear-{scene}")
        near, far = trainer.depth_range
        raw = mesh_depth(extract_mesh(trainer.field.eval(), trainer.volume, cfg.get("mc_resolution"), "cpu", depth_range=trainer.depth_range), scan.camera, "cpu")
        raw = np.where(valid & (raw >= near) & (raw <= far), raw, np.nan).astype(np.float32)
        pats = trainer.renderer.rendered_patterns.cpu().numpy()

        def finish(d):
            d1 = flying_pixel_filter(d, scan.camera, cfg.get("edge_filter"))
            d2 = photometric_filter(d1, scan.camera, scan.projector, scan.images, pats, (1.0 - cfg.get("min_confidence")))
            sigma_fn, _ = fit_model(scan, d2, "ls", "depth")
            d3 = refine_depth(scan, d2, sigma_fn, "ls", radius=3)
            out = {}
            for stage, dd in (("filtered", d2), ("refined", d3)):
                m = depth_metrics(dd, gt, scan.mask)
                out[stage] = {k: m[k] for k in ("mae", "median", "over_5mm", "completeness")}
                if scene == "rods":
                    rod = scan.mask & (gt < ROD_DEPTH_MM)
                    out[stage]["rod_completeness"] = float(np.isfinite(dd[rod]).mean())
                    e = np.abs(dd[rod] - gt[rod])
                    out[stage]["rod_within_5mm"] = float((e[np.isfinite(e)] < 5).mean()) if np.isfinite(e).any() else 0.0
            return out

        pipelines = {"trained": finish(raw)}
        sigma_raw, _ = fit_model(scan, raw, "ls", "depth")
        c_trained = pixel_cost(scan, raw, sigma_raw)
        for name in ("square 5x5, no confidence test", "adaptive windows, no confidence test"):
            ds = np.where(valid, searches[name], np.nan).astype(np.float32)
            c_search = pixel_cost(scan, ds, sigma_raw)
            switch = (c_search < 0.7 * c_trained) & (np.abs(ds - raw) > 5.0)
            pick = np.where(switch, ds, raw).astype(np.float32)
            pipelines[f"trained, or {name.split(',')[0]} where it explains the pixel better"] = {
                **finish(pick), "switched": float(switch[valid].mean())}
        doc["runs"].append({"scene": scene, "search": search_rows, "pipelines": pipelines, "gray": gray_code_yardstick(full),
                            "seconds": time.perf_counter() - t0})
        print(f"{scene}: done in {time.perf_counter() - t0:.0f} s", flush=True)
    write_study(args.out, doc, render_markdown)
    return 0


def render_markdown(doc: dict) -> str:
    a = doc["args"]
    lines = ["# Thin structures: where the rods are lost", "",
             f"`python bench/thin_structures.py --scenes {a['scenes']} --preset {a['preset']}` ({doc['date']}, CPU). Small "
             "rig, linear camera, the 6 random patterns of a random6+gray7 scan. 'rods': ground-truth pixels on a rod "
             f"(nearer than {ROD_DEPTH_MM:g} mm).", ""]
    for r in doc["runs"]:
        groups = list(next(iter(r["search"].values())))
        rows = [[name] + [f"{v[g]['within_5mm']:.1%} / {v[g]['wrong_over_5mm']:.1%} / {v[g]['no_answer']:.1%}" for g in groups]
                for name, v in r["search"].items()]
        lines += [f"## {r['scene']}: depth search (within 5 mm / wrong by > 5 mm / no answer)", ""]
        lines += markdown_table(["search"] + groups, rows) + [""]
        rod = r["scene"] == "rods"
        rows = []
        for name, p in r["pipelines"].items():
            for stage in ("filtered", "refined"):
                v = p[stage]
                rows.append([f"{name}, {stage}", f"{v['mae']:.3f}", f"{v['median']:.3f}", f"{v['over_5mm']:.2%}", f"{v['completeness']:.1%}"]
                            + ([f"{v['rod_completeness']:.1%}", f"{v['rod_within_5mm']:.1%}"] if rod else []))
        for g in ("GC(7) interp", "GC(6) interp"):
            m = r["gray"][g]
            rows.append([f"*{g}*", f"{m['mae']:.3f}", f"{m['median']:.3f}", f"{m['over_5mm']:.2%}", f"{m['completeness']:.1%}"]
                        + (["", ""] if rod else []))
        lines += [f"## {r['scene']}: trained field and per-pixel fallback", ""]
        lines += markdown_table(["depth", "MAE mm", "median mm", ">5 mm", "complete"]
                                + (["rod pixels with depth", "of which within 5 mm"] if rod else []), rows) + [""]
    return "\n".join(lines)


if __name__ == "__main__":
    raise SystemExit(main())
