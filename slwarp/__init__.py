"""slwarp: depth reconstruction with neural signed distance fields in camera + projector
structured-light systems, on fused NVIDIA Warp kernels (CPU and CUDA) around torch.

Public API (imported lazily, so `import slwarp` stays fast):
    Camera, Projector                      scanner geometry (slwarp.scans.scanner)
    Scan, load_scan, ScanError             scans on disk and in memory (slwarp.scans.scan)
    patterns                               pattern sets (slwarp.scans.patterns)
    simulate, simulate_scene, SimOptions   the virtual scanner (slwarp.sim.simulate)
    decode                                 classical decoders and triangulation (slwarp.decode)
    depth_metrics                          depth error metrics (slwarp.evaluation.metrics)
    render_structured_light, RenderOutput  the fused Warp renderer as a torch op (slwarp.neural.ops)
    StructuredLightRenderer                sampling + any SDF module + losses: a drop-in loss (slwarp.neural.render)
    NeuSField, LearnedVariance, Volume     the SDF network in mm (slwarp.neural.fields)
    HashGridSDF                            the hash-grid SDF field in mm (slwarp.neural.fields)
    TrainConfig, preset, load_config       the typed run configuration and its presets (slwarp.neural.config)
    Trainer                                training with the paper's schedule (slwarp.neural.training)
    reconstruct                            train, extract mesh and depth (slwarp.neural.reconstruct)
    search_depth                           depth by exhaustive search, the training's start (slwarp.neural.start.search)
"""
from __future__ import annotations

import importlib

__version__ = "0.1.0"

_LAZY = {
    "Camera": "slwarp.scans.scanner",
    "Projector": "slwarp.scans.scanner",
    "CalibrationError": "slwarp.scans.scanner",
    "Scan": "slwarp.scans.scan",
    "ScanError": "slwarp.scans.scan",
    "load_scan": "slwarp.scans.scan",
    "simulate": "slwarp.sim.simulate",
    "simulate_scene": "slwarp.sim.simulate",
    "SimOptions": "slwarp.sim.simulate",
    "make_rig": "slwarp.sim.rigs",
    "build_scene": "slwarp.sim.scenes",
    "render_structured_light": "slwarp.neural.ops",
    "RenderOutput": "slwarp.neural.ops",
    "StructuredLightRenderer": "slwarp.neural.render",
    "structured_light_losses": "slwarp.neural.render",
    "NeuSField": "slwarp.neural.fields",
    "LearnedVariance": "slwarp.neural.fields",
    "Volume": "slwarp.neural.fields",
    "HashGridSDF": "slwarp.neural.fields",
    "TrainConfig": "slwarp.neural.config",
    "load_config": "slwarp.neural.config",
    "Trainer": "slwarp.neural.training",
    "preset": "slwarp.neural.config",
    "reconstruct": "slwarp.neural.reconstruct",
    "search_depth": "slwarp.neural.start.search",
    "depth_metrics": "slwarp.evaluation.metrics",
}

_MODULES = {"patterns": "slwarp.scans.patterns", "metrics": "slwarp.evaluation.metrics", "decode": "slwarp.decode",
            "kernels": "slwarp.kernels"}


def __getattr__(name):
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    if name in _MODULES:
        return importlib.import_module(_MODULES[name])
    raise AttributeError(f"module 'slwarp' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + list(_LAZY))
