"""Shared set-up of the accuracy study scripts (bench/model_floor.py, bench/completeness.py,
bench/train_ablation.py): the study's scans, the Gray code yardstick and markdown tables.

Every study scan is one simulation with the paper's 6 random patterns and 7 Gray code bits ("random6+gray7",
pattern seed 0, noise seed 0) of a built-in scene on a built-in rig through a named camera model
(slwarp.sim.simulate.CAMERA_MODELS); the neural variants use its random frames, the yardstick decodes
GC(6) and GC(7) with interpolation from its Gray code frames.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

DATE = time.strftime("%Y-%m-%d")
GRAY_FRAMES = {"GC(7) interp": "gc_col_b[0-6]", "GC(6) interp": "gc_col_b[0-5]"}


def simulate_study_scan(scene: str, rig: str, camera: str = "linear", device: str = "cpu"):
    """(scan, SimOptions): scene on rig with the patterns random6+gray7 through a named camera model."""
    from slwarp.sim.simulate import camera_model, simulate_scene

    options = camera_model(camera)
    return simulate_scene(scene, "random6+gray7", rig=rig, options=options, device=device), options


def gray_code_yardstick(scan) -> dict:
    """{"GC(7) interp": metrics, "GC(6) interp": metrics} of gc-interp on the scan's column Gray code frames."""
    from slwarp.decode import reconstruct_depth
    from slwarp.evaluation.metrics import depth_metrics

    out = {}
    for name, frames in GRAY_FRAMES.items():
        depth, _, _ = reconstruct_depth(scan, "gc-interp", frames=frames)
        out[name] = depth_metrics(depth, scan.gt_depth, scan.mask)
    return out


def markdown_table(header: list[str], rows: list[list[str]]) -> list[str]:
    """Lines of a markdown table (first column left-aligned, the others right-aligned)."""
    lines = ["| " + " | ".join(header) + " |", "|---|" + "---:|" * (len(header) - 1)]
    lines += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return lines


def train_cached(scan, preset_name: str, variant: str, cache: Path, key: str, trainer_cls=None, **overrides):
    """(trainer, config, training seconds): a field trained on `scan` with a preset (CPU), kept in
    cache/<key>-<preset>-<variant>/checkpoint.pt and reloaded from there when it is complete. trainer_cls:
    a Trainer subclass (a model variant); overrides: TrainConfig fields."""
    from slwarp.neural.config import preset
    from slwarp.neural.train import Trainer

    cfg = preset(preset_name, device="cpu", **overrides)
    folder = Path(cache) / f"{key}-{preset_name}-{variant}"
    resume = (folder / "checkpoint.pt").is_file()
    trainer = (trainer_cls or Trainer)(scan, cfg, out_dir=folder, resume=resume, progress=False)
    t0 = time.perf_counter()
    trainer.train()
    return trainer, cfg, (time.perf_counter() - t0) if not resume else trainer.elapsed


def write_study(out, doc: dict, render) -> None:
    """Write a study's results: <out>.json (doc), <out>.md (render(doc)), and print the markdown."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(doc, indent=1, default=float))
    md = render(doc)
    out.with_suffix(".md").write_text(md)
    print(md)
