"""Where the neural method loses pixels and accuracy after training: completeness by stage and the depth
extraction method, on trained fields.

For each scene a field is trained with a preset (default `cpu`, small rig; cached in --cache so a second run
only evaluates), then:

1. Completeness by stage, over the scan's ground-truth pixels (hit and lit): the share each stage drops and the
   error those pixels would have had if kept (their depth just before the stage): the contrast mask (b <= the
   contrast threshold: never reconstructed), the marching-cubes mesh (no hit: a hole), the depth range, the
   flying-pixel filter and the photometric filter; the photometric drops split into pixels within 2 px of a
   ground-truth depth edge and the rest (the scattered holes on smooth surfaces).
2. Depth extraction: the depth of the same field from the marching-cubes mesh (the preset's resolution and
   twice it), from sphere tracing the SDF (sub-pixel, no mesh) and from the volume-rendered expected depth
   (sum_k w_k z_k, the quantity training fits); each raw (inside the valid mask and depth range) and after the
   flying-pixel and photometric filters.
3. Filter settings: the mesh depth under a grid of contrast thresholds, flying-pixel and photometric filter
   thresholds, reported as the mean over the scenes.

    python bench/extraction_study.py                                    # bunny, torus, checker, rods; small rig
    python bench/extraction_study.py --scenes bunny --preset tiny --out /tmp/x   # a quick look

Writes bench/results/extraction-cpu.{json,md} (or --out) and prints the tables.
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

from study_common import (DATE, gray_code_yardstick, markdown_table, simulate_study_scan,  # noqa: E402
                          train_cached, write_study)


def edge_pixels(gt: np.ndarray, camera, radius: int = 2, footprints: float = 10.0) -> np.ndarray:
    """[H, W] bool: pixels within `radius` px of a ground-truth depth jump larger than `footprints` pixel
    footprints (the flying-pixel filter's criterion, applied to the truth), or of a pixel with no truth."""
    H, W = gt.shape
    g = np.where(np.isfinite(gt), gt, 0.0)
    limit = footprints * np.nan_to_num(gt, nan=1e9) / min(camera.fx, camera.fy)
    pad = np.pad(g, radius, mode="edge")
    near = np.zeros((H, W), bool)
    for dy in range(2 * radius + 1):
        for dx in range(2 * radius + 1):
            near |= np.abs(pad[dy : dy + H, dx : dx + W] - g) > limit
    return near


def error_stats(depth: np.ndarray, gt: np.ndarray, sel: np.ndarray) -> dict:
    """MAE, median, share > 5 mm of |depth - gt| over `sel` where both are finite, and the pixel count."""
    ok = sel & np.isfinite(depth) & np.isfinite(gt)
    e = np.abs(depth[ok] - gt[ok])
    if e.size == 0:
        return {"n": 0, "mae": float("nan"), "median": float("nan"), "over_5mm": float("nan")}
    return {"n": int(e.size), "mae": float(e.mean()), "median": float(np.median(e)), "over_5mm": float((e > 5).mean())}


@torch.no_grad()
def rendered_depth(trainer, valid: np.ndarray, chunk: int = 2048) -> np.ndarray:
    """[H, W] volume-rendered expected depth (no jitter) of the valid pixels; NaN elsewhere."""
    r = trainer.renderer
    idx = torch.as_tensor(np.flatnonzero(valid.ravel()), device=trainer.device)
    out = torch.full((valid.size,), float("nan"), device=trainer.device)
    for s in range(0, idx.numel(), chunk):
        i = idx[s : s + chunk]
        with torch.enable_grad():
            o, _, _ = r.render(r.batch(i), perturb=False)
        out[i] = o.depth.detach()
    return out.reshape(valid.shape).cpu().numpy()


def study_field(trainer, scan, cfg) -> dict:
    """Stage drops and depth-extraction comparison for one trained field (see module docstring)."""
    from slwarp.neural.extraction.surface import extract_mesh, flying_pixel_filter, mesh_depth, sphere_trace_depth
    from slwarp.neural.pattern_model import photometric_filter

    cam, prj = scan.camera, scan.projector
    gt = scan.gt_depth.astype(np.float64)
    ref = scan.mask & np.isfinite(gt)
    n_gt = int(ref.sum())
    valid = trainer.renderer.valid_map.cpu().numpy()
    near, far = trainer.depth_range
    patterns = trainer.renderer.rendered_patterns.cpu().numpy()
    images = scan.images[: trainer.n_frames]
    edges = edge_pixels(scan.gt_depth, cam)
    field = trainer.field.eval()

    def in_range(d):
        d = np.where(valid, d, np.nan)
        return np.where((d >= near) & (d <= far), d, np.nan)

    def filters(d):
        f1 = flying_pixel_filter(d, cam, cfg.get("edge_filter")) if cfg.get("edge_filter") > 0 else d
        f2 = photometric_filter(f1, cam, prj, images, patterns, (1.0 - cfg.get("min_confidence"))) if (1.0 - cfg.get("min_confidence")) > 0 else f1
        return f1, f2

    t0 = time.perf_counter()
    depths = {}
    for res in (cfg.get("mc_resolution"), 2 * cfg.get("mc_resolution")):
        mesh = extract_mesh(field, trainer.volume, res, trainer.device, depth_range=trainer.depth_range)
        depths[f"mesh, marching cubes {res}"] = mesh_depth(mesh, cam, "cpu")
    depths["sphere tracing"] = sphere_trace_depth(field, cam, trainer.depth_range, trainer.device, valid=valid)
    depths["rendered expected depth"] = rendered_depth(trainer, valid)
    t_extract = time.perf_counter() - t0

    # 1. stages, on the preset's own pipeline (mesh at the preset's resolution)
    raw = depths[f"mesh, marching cubes {cfg.get('mc_resolution')}"]
    stages = {}
    keep = ref.copy()
    contrast_drop = keep & ~valid
    stages["contrast mask"] = {"share": contrast_drop.sum() / n_gt, **error_stats(raw, gt, contrast_drop)}
    keep &= valid
    hole = keep & ~np.isfinite(raw)
    stages["mesh hole (no hit)"] = {"share": hole.sum() / n_gt, "n": int(hole.sum())}
    keep &= np.isfinite(raw)
    rng_drop = keep & ~np.isfinite(in_range(raw))
    stages["depth range"] = {"share": rng_drop.sum() / n_gt, **error_stats(raw, gt, rng_drop)}
    d0 = in_range(raw)
    keep &= np.isfinite(d0)
    d1, d2 = filters(d0)
    fly = keep & ~np.isfinite(d1)
    stages["flying-pixel filter"] = {"share": fly.sum() / n_gt, **error_stats(d0, gt, fly),
                                     "near_edge_share": float((fly & edges).sum() / max(fly.sum(), 1))}
    keep &= np.isfinite(d1)
    photo = keep & ~np.isfinite(d2)
    stages["photometric filter"] = {"share": photo.sum() / n_gt, **error_stats(d1, gt, photo),
                                    "near_edge": error_stats(d1, gt, photo & edges),
                                    "interior": error_stats(d1, gt, photo & ~edges)}
    keep &= np.isfinite(d2)
    stages["kept"] = {"share": keep.sum() / n_gt, **error_stats(d2, gt, keep),
                      "near_edge": error_stats(d2, gt, keep & edges), "interior": error_stats(d2, gt, keep & ~edges)}

    # 2. extraction methods, raw and filtered, on the ground-truth pixels
    methods = {}
    for name, d in depths.items():
        dr = in_range(d)
        f1, f2 = filters(dr)
        methods[name] = {
            "raw": {**error_stats(dr, gt, ref), "completeness": float((ref & np.isfinite(dr)).sum() / n_gt)},
            "filtered": {**error_stats(f2, gt, ref), "completeness": float((ref & np.isfinite(f2)).sum() / n_gt)},
            "interior_raw": error_stats(dr, gt, ref & ~edges),
        }
    # the same pixels for every method: where all four gave a depth (raw), so that methods compare fairly
    common = ref & np.logical_and.reduce([np.isfinite(in_range(d)) for d in depths.values()])
    for name, d in depths.items():
        methods[name]["common_pixels"] = error_stats(in_range(d), gt, common)
    field.train()
    return {"n_gt": n_gt, "edge_share": float((edges & ref).sum() / n_gt), "stages": stages, "methods": methods,
            "filters": filter_sweep(raw, scan, trainer), "extract_s": t_extract}


CONTRAST = (0.05, 0.03, 0.02)
FLYING = (10.0, 20.0, 0.0)
PHOTOMETRIC = (0.3, 0.4, 0.5, 0.6, 0.0)


def filter_sweep(raw: np.ndarray, scan, trainer) -> list[dict]:
    """Metrics of the mesh depth for every (contrast threshold, flying-pixel footprints, photometric threshold)
    of the grids above (0 = off). The field is the one trained with the preset's contrast threshold; a lower
    threshold here only keeps more pixels at extraction."""
    from slwarp.evaluation.metrics import depth_metrics
    from slwarp.neural.extraction.surface import flying_pixel_filter
    from slwarp.neural.pattern_model import photometric_filter

    cam, prj = scan.camera, scan.projector
    images = scan.images[: trainer.n_frames]
    b = images.max(0) - images.min(0)
    near, far = trainer.depth_range
    patterns = trainer.renderer.rendered_patterns.cpu().numpy()
    rows = []
    for ct in CONTRAST:
        d0 = np.where((b > ct) & (raw >= near) & (raw <= far), raw, np.nan).astype(np.float32)
        for fly in FLYING:
            d1 = flying_pixel_filter(d0, cam, fly) if fly > 0 else d0
            for ph in PHOTOMETRIC:
                d2 = photometric_filter(d1, cam, prj, images, patterns, ph) if ph > 0 else d1
                m = depth_metrics(d2, scan.gt_depth, scan.mask)
                rows.append({"contrast": ct, "flying": fly, "photometric": ph,
                             **{k: m[k] for k in ("mae", "median", "over_5mm", "completeness")}})
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", default="bunny,torus,checker,rods")
    ap.add_argument("--rig", default="small")
    ap.add_argument("--camera", default="linear", help="camera model (slwarp.sim.simulate.CAMERA_MODELS)")
    ap.add_argument("--preset", default="cpu")
    ap.add_argument("--cache", default="/tmp/slwarp-study-fields", help="trained fields are kept here and reused")
    ap.add_argument("--out", default=str(REPO / "bench" / "results" / "extraction-cpu"))
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    doc = {"date": DATE, "machine": platform.processor() or platform.machine(), "args": vars(args), "runs": []}
    for scene in args.scenes.split(","):
        t0 = time.perf_counter()
        scan, _ = simulate_study_scan(scene, args.rig, args.camera)
        trainer, cfg, train_s = train_cached(scan.select("rand*"), args.preset, "baseline", Path(args.cache),
                                             key=f"{args.rig}-{args.camera}-{scene}")
        res = study_field(trainer, scan.select("rand*"), cfg)
        res.update(scene=scene, gray=gray_code_yardstick(scan), train_s=train_s, seconds=time.perf_counter() - t0)
        doc["runs"].append(res)
        k = res["stages"]["kept"]
        print(f"{scene}: kept {k['share']:.1%} MAE {k['mae']:.3f} ({res['seconds']:.0f} s)", flush=True)
    write_study(args.out, doc, render_markdown)
    return 0


def render_markdown(doc: dict) -> str:
    a = doc["args"]
    lines = ["# Completeness by stage and depth extraction on trained fields", "",
             f"`python bench/extraction_study.py --scenes {a['scenes']} --rig {a['rig']} --camera {a['camera']} --preset "
             f"{a['preset']}` ({doc['date']}, CPU). Fields trained on the 6 random patterns of a random6+gray7 scan "
             "(pattern and noise seed 0). Shares are of the scan's ground-truth pixels; the error columns are those "
             "of the dropped pixels had they been kept (their depth just before the stage). 'edge': within 2 px of "
             "a ground-truth depth jump of more than 10 pixel footprints.", ""]
    for r in doc["runs"]:
        st = r["stages"]
        rows = []
        for name, v in st.items():
            if name == "photometric filter":
                rows.append([name, f"{v['share']:.2%}", v["n"], f"{v['mae']:.3f}", f"{v['median']:.3f}", f"{v['over_5mm']:.1%}"])
                for part in ("near_edge", "interior"):
                    p = v[part]
                    rows.append([f"  of which {part.replace('_', ' ')}", f"{p['n'] / r['n_gt']:.2%}", p["n"], f"{p['mae']:.3f}",
                                 f"{p['median']:.3f}", f"{p['over_5mm']:.1%}"])
            elif "mae" in v:
                rows.append([name, f"{v['share']:.2%}", v["n"], f"{v['mae']:.3f}", f"{v['median']:.3f}", f"{v['over_5mm']:.1%}"])
            else:
                rows.append([name, f"{v['share']:.2%}", v["n"], "-", "-", "-"])
        g7 = r["gray"]["GC(7) interp"]
        lines += [f"## {r['scene']}: completeness by stage (GT pixels {r['n_gt']}, {r['edge_share']:.1%} near an edge; "
                  f"GC(7)-interp: MAE {g7['mae']:.3f}, completeness {g7['completeness']:.1%})", ""]
        lines += markdown_table(["stage", "share of GT pixels", "pixels", "MAE mm", "median mm", ">5 mm"], rows) + [""]
        rows = []
        for name, m in r["methods"].items():
            rows.append([name, f"{m['raw']['mae']:.3f}", f"{m['raw']['median']:.3f}", f"{m['raw']['over_5mm']:.2%}",
                         f"{m['raw']['completeness']:.1%}", f"{m['common_pixels']['mae']:.3f}", f"{m['common_pixels']['median']:.3f}",
                         f"{m['interior_raw']['mae']:.3f}",
                         f"{m['filtered']['mae']:.3f}", f"{m['filtered']['over_5mm']:.2%}", f"{m['filtered']['completeness']:.1%}"])
        lines += [f"## {r['scene']}: depth extraction from the same field", ""]
        lines += markdown_table(["method", "raw MAE", "raw median", "raw >5 mm", "raw complete", "common-pixel MAE",
                                 "common-pixel median", "interior raw MAE", "filtered MAE", "filtered >5 mm",
                                 "filtered complete"], rows) + [""]
    # filter settings: the mean over the scenes (never one scene's best)
    runs = doc["runs"]
    if runs and "filters" in runs[0]:
        keys = [(f["contrast"], f["flying"], f["photometric"]) for f in runs[0]["filters"]]
        g7 = [r["gray"]["GC(7) interp"] for r in runs]
        rows = []
        for i, (ct, fly, ph) in enumerate(keys):
            vals = {k: float(np.mean([r["filters"][i][k] for r in runs])) for k in ("mae", "median", "over_5mm", "completeness")}
            rows.append([f"{ct:g}", f"{fly:g}" if fly else "off", f"{ph:g}" if ph else "off", f"{vals['mae']:.3f}",
                         f"{vals['median']:.3f}", f"{vals['over_5mm']:.2%}", f"{vals['completeness']:.1%}"]
                        + [f"{r['filters'][i]['mae']:.3f} / {r['filters'][i]['completeness']:.1%}" for r in runs])
        rows.append(["*GC(7) interp*", "", "", f"{np.mean([g['mae'] for g in g7]):.3f}", f"{np.mean([g['median'] for g in g7]):.3f}",
                     f"{np.mean([g['over_5mm'] for g in g7]):.2%}", f"{np.mean([g['completeness'] for g in g7]):.1%}"]
                    + [f"{g['mae']:.3f} / {g['completeness']:.1%}" for g in g7])
        lines += ["## Extraction filters: mean over the scenes (mesh depth of the same fields)", "",
                  "Contrast threshold on b = max - min (the field was trained with 0.05), flying-pixel filter in pixel "
                  "footprints, photometric filter's relative RMS threshold (min/max a, b; the fitted global blur); 'off' = "
                  "not applied. Per-scene columns: MAE mm / completeness.", ""]
        lines += markdown_table(["contrast", "flying", "photometric", "mean MAE", "mean median", "mean >5 mm",
                                 "mean complete"] + [r["scene"] for r in runs], rows) + [""]
    return "\n".join(lines)


if __name__ == "__main__":
    raise SystemExit(main())
