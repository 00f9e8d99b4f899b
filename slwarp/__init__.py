"""slwarp: depth reconstruction with neural signed distance fields in camera + projector
structured-light systems, on fused NVIDIA Warp kernels (CPU and CUDA) around torch.

Public API (imported lazily, so `import slwarp` stays fast):
    Camera, Projector                      scanner geometry (slwarp.scanner)
    Scan, load_scan, ScanError             scans on disk and in memory (slwarp.scan)
    patterns                               pattern sets (slwarp.patterns)
    simulate, simulate_scene, SimOptions   the virtual scanner (slwarp.simulate)
    decode                                 classical decoders and triangulation (slwarp.decode)
    depth_metrics                          depth error metrics (slwarp.metrics)
    render_structured_light, RenderOutput  the fused Warp renderer as a torch op (slwarp.ops)
    StructuredLightRenderer                sampling + any SDF module + losses: a drop-in loss (slwarp.render)
    NeuSField, LearnedVariance, Volume     the SDF network in mm (slwarp.field)
    Trainer, TrainConfig, preset           training with the paper's schedule (slwarp.train)
    reconstruct                            train, extract mesh and depth (slwarp.reconstruct)
    search_depth                           depth by exhaustive search, the training's start (slwarp.search)
"""
from __future__ import annotations

import importlib

__version__ = "0.1.0"

_LAZY = {
    "Camera": "slwarp.scanner",
    "Projector": "slwarp.scanner",
    "CalibrationError": "slwarp.scanner",
    "Scan": "slwarp.scan",
    "ScanError": "slwarp.scan",
    "load_scan": "slwarp.scan",
    "simulate": "slwarp.simulate",
    "simulate_scene": "slwarp.simulate",
    "SimOptions": "slwarp.simulate",
    "make_rig": "slwarp.rigs",
    "build_scene": "slwarp.scenes",
    "render_structured_light": "slwarp.ops",
    "RenderOutput": "slwarp.ops",
    "StructuredLightRenderer": "slwarp.render",
    "structured_light_losses": "slwarp.render",
    "NeuSField": "slwarp.field",
    "LearnedVariance": "slwarp.field",
    "Volume": "slwarp.field",
    "TrainConfig": "slwarp.train",
    "Trainer": "slwarp.train",
    "preset": "slwarp.train",
    "reconstruct": "slwarp.reconstruct",
    "search_depth": "slwarp.search",
    "depth_metrics": "slwarp.metrics",
}


def __getattr__(name):
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    if name in ("patterns", "decode", "metrics", "kernels"):
        return importlib.import_module(f"slwarp.{name}")
    raise AttributeError(f"module 'slwarp' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + list(_LAZY))
