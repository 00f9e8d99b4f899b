"""`slwarp demo`: the paper's comparison on an embedded default scene, end to end.

Simulates the default scene with the paper's 6 random patterns and with 7-bit Gray code (one scan, the
two pattern sets side by side), reconstructs depth with the neural SDF from the 6 random patterns,
decodes GC(6) and GC(7) with interpolation from the Gray code frames, and prints a table in the style of
the paper's Table 1. Writes into the output folder: the scan, each method's depth map and error map, a
side-by-side comparison figure, a point-cloud picture and results.json.

With a GPU: the default rig (camera 1280x1024) and the GPU's default preset (accurate). Without: the
small rig (camera 320x256) and the CPU's (cpu-hashgrid), a few minutes on two cores.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

DEMO_SCENE = "bunny"


def comparison_figure(path, gt, results: dict, max_err: float = 3.0) -> None:
    """GT depth and, per method, its depth and error map (matplotlib PNG), with a colour bar in mm for each row."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(results)
    lo, hi = np.nanpercentile(gt, [1, 99])
    fig, axes = plt.subplots(2, len(names) + 1, figsize=(3.6 * (len(names) + 1), 6.2), dpi=100)
    cm_d = matplotlib.colormaps["turbo"].with_extremes(bad=(0.1, 0.1, 0.1))
    cm_e = matplotlib.colormaps["inferno"].with_extremes(bad=(0.1, 0.1, 0.1))
    shown = axes[0, 0].imshow(np.ma.masked_invalid(gt), cmap=cm_d, vmin=lo, vmax=hi)
    axes[0, 0].set_title("ground truth depth", fontsize=9)
    axes[1, 0].axis("off")
    axes[1, 0].text(0.0, 0.5, f"depth colour range\n{lo:.0f} .. {hi:.0f} mm\n\nerror colour range\n0 .. {max_err:g} mm",
                    fontsize=9, va="center")
    for j, name in enumerate(names, start=1):
        d, m = results[name]["depth"], results[name]["metrics"]
        axes[0, j].imshow(np.ma.masked_invalid(d), cmap=cm_d, vmin=lo, vmax=hi)
        axes[0, j].set_title(f"{name}", fontsize=9)
        im = axes[1, j].imshow(np.ma.masked_invalid(np.abs(d - gt)), cmap=cm_e, vmin=0, vmax=max_err)
        axes[1, j].set_title(f"|error|: MAE {m['mae']:.3f} mm", fontsize=9)
    for ax in axes.ravel():
        ax.set_xticks([])
        ax.set_yticks([])
    fig.colorbar(shown, ax=axes[0, :].tolist(), fraction=0.02, pad=0.01, label="depth mm")
    fig.colorbar(im, ax=axes[1, :].tolist(), fraction=0.02, pad=0.01, label="error mm")
    fig.savefig(path, bbox_inches="tight")
    plt.close(fig)


def run_demo(out_dir="slwarp-demo", scene: str = DEMO_SCENE, config=None, preset_name: str | None = None,
             progress: bool = True, log=print) -> dict:
    """Run the demo (see module docstring) and return its results dict (also written to results.json).

    config: the TrainConfig of the neural SDF (default: preset `preset_name`, else the device's default preset);
    its runtime.device picks the rig: the default rig on CUDA, the small one on the CPU."""
    import torch

    from .devices import torch_device, warp_device
    from .evaluation.metrics import format_table
    from .neural.config import default_preset_name, preset
    from .neural.describe import describe
    from .neural.reconstruct import reconstruct
    from .sim.simulate import simulate_scene

    t0 = time.perf_counter()
    if config is None:
        preset_name = preset_name or default_preset_name(torch_device("auto"))
        config = preset(preset_name)
    cfg = config
    dev = torch_device(cfg.runtime.device)
    cfg = cfg.with_options(device=str(dev))
    gpu = dev.type == "cuda"
    rig = "default" if gpu else "small"
    preset_name = preset_name or "custom"
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    log(f"slwarp demo: scene '{scene}', {rig} rig, preset '{preset_name}' ({describe(cfg)}), device {dev}")

    log("1/4 simulating the scan (paper's 6 random patterns + 7-bit Gray code) ...")
    scan = simulate_scene(scene, "random6+gray7", rig=rig, device=warp_device(dev))
    scan.save(out / "scan")
    t_sim = time.perf_counter()

    log("2/4 neural SDF from the 6 random patterns ...")
    ours = reconstruct(scan.select("rand*"), cfg, out_dir=out / "neural-sdf", progress=progress,
                       overwrite=True)  # a demo starts afresh each time
    t_ours = time.perf_counter()

    log("3/4 classical Gray code decoding with interpolation: GC(6) and GC(7) ...")
    results = {"ours (6 random)": {"depth": ours.depth, "metrics": ours.metrics, "patterns": 6}}
    results.update(_gray_code_baselines(scan, out))
    t_gc = time.perf_counter()

    log("4/4 pictures ...")
    gt = scan.gt_depth.astype(np.float64)
    _save_pictures(out, scan, gt, results)
    t_end = time.perf_counter()

    rows = [(f"{k} [{v['patterns']} patterns]", v["metrics"]) for k, v in results.items()]
    table = format_table(rows)
    ratio = {k: results["ours (6 random)"]["metrics"]["mae"] / v["metrics"]["mae"] for k, v in results.items() if k.startswith("GC")}
    summary = {
        "scene": scene, "rig": rig, "preset": preset_name, "iterations": cfg.schedule.iters, "device": str(dev),
        "device_name": torch.cuda.get_device_name(dev) if gpu else "cpu",
        "metrics": {k: v["metrics"] for k, v in results.items()},
        "ours_mae_over": ratio,
        "timings_s": {"simulate": t_sim - t0, "neural_sdf_total": t_ours - t_sim, "neural_sdf_train": ours.timings["train_s"],
                      "classical": t_gc - t_ours, "pictures": t_end - t_gc, "total": t_end - t0},
    }
    (out / "results.json").write_text(json.dumps(summary, indent=1, default=float))
    (out / "table.md").write_text(table + "\n")
    log("")
    log(f"Depth error against exact ground truth ({scene}, {rig} rig, {int(np.isfinite(gt).sum())} GT pixels):")
    log(table)
    log("ours / GC MAE: " + ", ".join(f"{k}: {v:.2f}x" for k, v in ratio.items()))
    log(f"time: simulate {t_sim - t0:.1f} s, neural SDF {t_ours - t_sim:.1f} s (training {ours.timings['train_s']:.1f} s), "
        f"classical {t_gc - t_ours:.1f} s, pictures {t_end - t_gc:.1f} s, total {t_end - t0:.1f} s")
    log(f"wrote {out}/: comparison.png, point_cloud.png, table.md, results.json, scan/, neural-sdf/, gc6-interp/, gc7-interp/")
    return summary


# each method's output folder in the demo's
_FOLDERS = {"ours (6 random)": "neural-sdf", "GC(6) interp": "gc6-interp", "GC(7) interp": "gc7-interp"}


def _gray_code_baselines(scan, out: Path) -> dict:
    """GC(6) and GC(7) with interpolation from the scan's column Gray code frames, each written (depth, metrics.json)
    into out/gc{bits}-interp/: {method: {"depth", "metrics", "patterns"}}."""
    from .decode import reconstruct_depth
    from .evaluation.metrics import depth_metrics
    from .evaluation.outputs import write_depth

    results = {}
    for bits in (6, 7):
        frames = ",".join(f"gc_col_b{i}" for i in range(bits))
        depth, _, _ = reconstruct_depth(scan, "gc-interp", frames=frames)
        folder = out / f"gc{bits}-interp"
        folder.mkdir(exist_ok=True)
        write_depth(folder, depth)
        m = depth_metrics(depth, scan.gt_depth, scan.mask)
        (folder / "metrics.json").write_text(json.dumps({"method": "gc-interp", "frames": frames.split(","), "metrics": m}, indent=1))
        results[f"GC({bits}) interp"] = {"depth": depth, "metrics": m, "patterns": bits}
    return results


def _save_pictures(out: Path, scan, gt: np.ndarray, results: dict) -> None:
    """Each method's depth colour picture and error map in its folder, comparison.png and the neural SDF's
    point_cloud.png."""
    from .evaluation.viz import save_depth_color, save_error_map, save_point_cloud_render
    from .neural.depth_maps import depth_to_points

    lo_hi = (np.nanpercentile(gt, 1), np.nanpercentile(gt, 99))
    for name, r in results.items():
        folder = out / _FOLDERS[name]
        save_depth_color(folder / "depth_color.png", r["depth"], lo_hi)
        save_error_map(folder / "error_map.png", np.where(scan.mask, r["depth"], np.nan), gt,
                       title=f"{name}: |depth error|, MAE {r['metrics']['mae']:.3f} mm", max_mm=3.0)
    comparison_figure(out / "comparison.png", np.where(scan.mask, gt, np.nan),
                      {k: {"depth": np.where(scan.mask, v["depth"], np.nan), "metrics": v["metrics"]} for k, v in results.items()})
    pts = depth_to_points(results["ours (6 random)"]["depth"], scan.camera)
    save_point_cloud_render(out / "point_cloud.png", pts, title=f"neural SDF point cloud ({len(pts)} points)")
