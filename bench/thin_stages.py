"""Where a thin part is lost, stage by stage: the depth search that starts training, the field after the warm-up,
the trained field (marching-cubes mesh and sphere tracing) and the extracted depth map.

For the `rods` scene (2.5 mm rods nearer than 685 mm, every other surface farther), per stage: the share of the rod
pixels and of the other pixels of the GT mask whose depth is within 5 mm of the truth ("ok"), off by more
("wrong") or missing ("none"); after the warm-up and after training, the field's SDF at the rods' true surface
points (median, and the share within 1.5 mm of zero: 0 mm median means the field holds the rods). Any scene works;
without rods only the "rest" columns mean anything.

    python bench/thin_stages.py --rig default --preset tuned            # GPU (several minutes on an H100)
    python bench/thin_stages.py --rig small --preset cpu-hashgrid       # CPU

Writes <out>/thin-stages-<scene>-<rig>-<preset>.{json,md}.
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

from study_common import DATE, markdown_table, write_study  # noqa: E402

ROD_DEPTH_MM = 685.0  # every rod of the `rods` scene lies nearer than this, every other surface farther
OK_MM = 5.0
STAGES = ("search", "warm-up mesh", "trained mesh", "trained sphere tracing", "extracted")


def shares(depth, gt, part) -> dict:
    """ok / wrong / none shares of the pixels in `part` and the MAE of the ok ones (mm)."""
    d = np.asarray(depth, np.float64).reshape(gt.shape)
    e = np.abs(d - gt)
    n = max(int(part.sum()), 1)
    ok = part & (e <= OK_MM)
    return {"ok": float(ok.sum() / n), "wrong": float((part & (e > OK_MM)).sum() / n),
            "none": float((part & ~np.isfinite(d)).sum() / n), "mae_ok": float(e[ok].mean()) if ok.any() else None}


def sdf_at_surface(trainer, scan, part) -> dict:
    """The field's SDF (mm) at the true surface points of the pixels in `part`: median and share within 1.5 mm."""
    if not part.any():
        return {"median": None, "near": None}
    rays = scan.camera.pixel_to_ray(scan.camera.pixel_grid())[part]
    pts = rays / rays[:, 2:3] * scan.gt_depth[part][:, None]
    with torch.no_grad():
        f = trainer.field(torch.as_tensor(pts, dtype=torch.float32, device=trainer.device)).reshape(-1).cpu().numpy()
    return {"median": float(np.median(f)), "near": float((np.abs(f) < 1.5).mean())}


def run(scene: str, rig: str, preset_name: str, overrides: dict, device: str) -> dict:
    from slwarp.neural.config import preset
    from slwarp.neural.extraction.surface import extract_mesh, mesh_depth, sphere_trace_depth
    from slwarp.neural.extraction import extract_depth
    from slwarp.neural.train import Trainer
    from slwarp.sim.simulate import SimOptions, simulate_scene

    t0 = time.perf_counter()
    scan = simulate_scene(scene, "random6", rig, SimOptions(seed=0))
    gt, mask = scan.gt_depth, scan.mask & np.isfinite(scan.gt_depth)
    thin = mask & (gt < ROD_DEPTH_MM) if scene == "rods" else np.zeros_like(mask)
    parts = {"rods": thin, "rest": mask & ~thin}
    cfg = preset(preset_name, device=device, **overrides)
    tr = Trainer(scan, cfg, progress=False)
    doc = {"date": DATE, "scene": scene, "rig": rig, "preset": preset_name, "overrides": overrides,
           "device": str(tr.device), "thin_px": int(thin.sum()), "stages": {}, "sdf": {}}

    def stage(name, depth):
        doc["stages"][name] = {k: shares(depth, gt, p) for k, p in parts.items()}

    def mesh_stage(name):
        field = tr.field.eval()
        stage(name, mesh_depth(extract_mesh(field, tr.volume, cfg.extraction.mc_resolution, tr.device, depth_range=tr.depth_range), scan.camera, tr.device))
        field.train()

    if tr.init_depth is not None:
        stage("search", tr.init_depth.cpu().numpy())
    tr.train(iters=tr.warmup_iters)
    doc["sdf"]["warm-up"] = sdf_at_surface(tr, scan, thin)
    mesh_stage("warm-up mesh")
    tr.train()
    doc["sdf"]["trained"] = sdf_at_surface(tr, scan, thin)
    mesh_stage("trained mesh")
    stage("trained sphere tracing", sphere_trace_depth(tr.field.eval(), scan.camera, tr.depth_range, tr.device))
    tr.field.train()
    depth, _, _, timings, _ = extract_depth(tr, tr.renderer.valid_map.cpu().numpy())
    stage("extracted", depth)
    e = np.abs(depth - gt)
    ok = mask & np.isfinite(e)
    doc["extracted"] = {"mae": float(e[ok].mean()), "completeness": float(ok.sum() / mask.sum()),
                        "dropped": timings["dropped"], "repair": timings["repair"]}
    doc["wall_s"] = time.perf_counter() - t0
    return doc


def render(doc: dict) -> str:
    pct = lambda x: f"{100 * x:.1f}%"  # noqa: E731
    rows = []
    for name in STAGES:
        s = doc["stages"].get(name)
        if s is None:
            continue
        rows.append([name] + [pct(s[p][k]) for p in ("rods", "rest") for k in ("ok", "wrong", "none")]
                    + [f"{s['rods']['mae_ok']:.3f}" if s["rods"]["mae_ok"] is not None else "-",
                       f"{s['rest']['mae_ok']:.3f}" if s["rest"]["mae_ok"] is not None else "-"])
    lines = [f"# Where a thin part is lost: {doc['scene']} on the {doc['rig']} rig, preset {doc['preset']} "
             f"({doc['device']}, {doc['date']})", "",
             f"`python bench/thin_stages.py --scene {doc['scene']} --rig {doc['rig']} --preset {doc['preset']}"
             + (" --set " + ",".join(f"{k}={v}" for k, v in doc["overrides"].items()) if doc["overrides"] else "") + f"`; {doc['wall_s']:.0f} s. "
             f"Rod pixels: GT depth < {ROD_DEPTH_MM:.0f} mm ({doc['thin_px']} px); rest: the other pixels of the GT "
             f"mask. ok: within {OK_MM:.0f} mm; MAE of the ok pixels in mm.", ""]
    lines += markdown_table(["stage", "rods ok", "rods wrong", "rods none", "rest ok", "rest wrong", "rest none",
                             "rods MAE ok", "rest MAE ok"], rows)
    lines += ["", "The field's SDF at the rods' true surface points (mm): "
              + "; ".join(f"{k}: median {v['median']:.1f}, within 1.5 mm {pct(v['near'])}"
                          for k, v in doc["sdf"].items() if v["median"] is not None), "",
              f"Extracted: MAE {doc['extracted']['mae']:.3f} mm, completeness {pct(doc['extracted']['completeness'])}, "
              f"dropped per stage {doc['extracted']['dropped']}, search repair {doc['extracted']['repair']}.", ""]
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="rods")
    ap.add_argument("--rig", default="default")
    ap.add_argument("--preset", default="tuned")
    ap.add_argument("--set", default="", metavar="KEY=VALUE,...", help="TrainConfig options, e.g. 'iters=300,rays=512'")
    ap.add_argument("--device", default="auto")
    ap.add_argument("--out", default=str(REPO / "bench" / "results"))
    args = ap.parse_args(argv)
    from accuracy_sweep import parse_overrides

    overrides = parse_overrides(args.set)
    doc = run(args.scene, args.rig, args.preset, overrides, args.device)
    write_study(Path(args.out) / f"thin-stages-{args.scene}-{args.rig}-{args.preset}", doc, render)


if __name__ == "__main__":
    main()
