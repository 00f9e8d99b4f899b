"""The working volume (`Volume`): the axis-aligned box in the camera frame (mm) that a field is normalised to, and
the per-scan numbers a field's forward reads from it as tensors (`register_volume_buffers`)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn as nn


@dataclass(frozen=True)
class Volume:
    """Axis-aligned working volume in the camera frame (mm): lo [3], hi [3]."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]

    @property
    def center(self) -> np.ndarray:
        return (np.asarray(self.lo) + np.asarray(self.hi)) / 2

    @property
    def scale(self) -> float:
        """Half the largest side (mm): the box fits in [-1, 1]^3 after (x - center) / scale.
        Plain Python arithmetic: torch.compile traces through it without a graph break (through numpy it broke
        the trainer's compiled map terms into six graphs)."""
        return max(float(h) - float(l) for l, h in zip(self.lo, self.hi)) / 2

    def as_bounds(self) -> list[list[float]]:
        return [list(map(float, self.lo)), list(map(float, self.hi))]

    @classmethod
    def from_frustum(cls, camera, valid: np.ndarray, depth_range, margin: float = 0.02) -> "Volume":
        """Box around the camera frustum of the `valid` pixels [H, W] between the near and far depth."""
        v, u = np.nonzero(valid)
        if u.size == 0:
            raise ValueError("no valid pixel to define the working volume")
        step = max(1, u.size // 20000)  # a subsample of the valid pixels bounds the frustum well enough
        d = camera.pixel_to_ray(np.stack([u[::step], v[::step]], -1).astype(np.float64))
        d = d / d[:, 2:3]  # points at unit depth
        corners = np.concatenate([d * depth_range[0], d * depth_range[1]])
        lo, hi = corners.min(0), corners.max(0)
        pad = (hi - lo).max() * margin
        return cls(tuple((lo - pad).tolist()), tuple((hi + pad).tolist()))


def register_volume_buffers(module: nn.Module, volume: Volume, far: float | None) -> None:
    """Give an SDF module the per-scan numbers its forward reads: `center` [3] (float32, saved with the weights),
    and, not saved, `scale_mm` (the volume's scale) and `prior_mm` (the camera prior's radius `far`, when given) as
    0-d float32 buffers (float32 as a Python float meets a float32 tensor). As tensors they are inputs of
    torch.compile's graphs, not constants: the graphs compiled for one scan serve the next scan of the same
    sizes (as floats, every working volume recompiled them)."""
    module.register_buffer("center", torch.tensor(volume.center, dtype=torch.float32))
    module.register_buffer("scale_mm", torch.tensor(float(volume.scale), dtype=torch.float32), persistent=False)
    if far is not None:
        module.register_buffer("prior_mm", torch.tensor(float(far), dtype=torch.float32), persistent=False)
