"""The photometric confidence of a depth map, which the training (its surface term) and the extraction share,
and a trainer's frames as the pattern model holds them.

`photometric_confidence`: 1 - r, r the relative RMS residual of the pattern model at the pixel's depth
(`pattern_model.photometric_residual`: how much of the modulation b the predicted codes leave unexplained), a map
[H, W] float32 in [0, 1], NaN where the depth map has no depth. The other confidence terms, and the confidence map
an extraction writes, are in `slwarp.neural.extraction.confidence`.
"""
from __future__ import annotations

import numpy as np

from .depth_maps import on_depth
from .pattern_model import photometric_residual

__all__ = ["photometric_confidence", "pattern_model_inputs", "on_depth"]


def photometric_confidence(depth: np.ndarray, camera, projector, images, patterns) -> np.ndarray:
    """[H, W]: 1 - relative RMS residual of the pattern model at depth (mm; NaN invalid). images [N, H, W],
    patterns [N, Hp, Wp] as rendered (blurred): numpy, or tensors on the device to compute on
    (`pattern_model.photometric_residual`)."""
    return on_depth(1.0 - photometric_residual(depth, camera, projector, images, patterns), depth)


def pattern_model_inputs(trainer) -> tuple:
    """(images [N, H, W], patterns as rendered [N, Hp, Wp]) of a trainer's frames for the pattern model
    (photometric_confidence, the depth searches): on a GPU the renderer's own tensors, so that the model runs
    there (pattern_model._residual_on_device); else numpy, on the host."""
    patterns = trainer.renderer.rendered_patterns.detach()
    if trainer.device.type == "cuda":
        cam = trainer.scan.camera
        return trainer.renderer.images_flat.t().reshape(-1, cam.height, cam.width), patterns
    return trainer.scan.images[: trainer.n_frames], patterns.cpu().numpy()
