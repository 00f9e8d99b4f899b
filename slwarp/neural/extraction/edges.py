"""The pixels beside a depth edge settled by their codes: each keeps its depth, takes the depth across the edge, or
is dropped, as its images say (`settle_edge_sides`).

Why: where the field misses part of a thin object or draws its outline a pixel off, a band of pixels one or two
wide keeps the other surface's depth, 200-360 mm off. The flying-pixel filter does not see them: it compares
neighbours, and theirs were dropped (their codes did not fit), lie in a shadow, or carry the same wrong depth. The
repair and the fill later give depths to the pixels around, so that in the finished map the band sits beside the
right surface. Full-resolution rods, `cpu-hashgrid` (default rig; 2-core CPU): 765 pixels off by more than 5 mm,
0.08% of the map, give its RMSE of 6.3 mm and a quarter of its MAE; 329 of them have a depth across a jump within
one pixel, 490 within two.
"""
from __future__ import annotations

import numpy as np

from ..pattern_model import photometric_residual
from .state import ModelInputs

__all__ = ["settle_edge_sides"]


def _window_offsets(radius: int) -> list[tuple[int, int]]:
    return [(dy, dx) for dy in range(-radius, radius + 1) for dx in range(-radius, radius + 1) if (dy, dx) != (0, 0)]


def settle_edge_sides(depth: np.ndarray, inputs: ModelInputs, radius: int, margin: float,
                      footprints: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(depth [H, W] mm, switched [H, W] bool, dropped [H, W] bool) after settling each pixel with a depth across an
    edge: a pixel of its (2 radius + 1)^2 window whose depth differs from its own by more than `footprints` pixel
    footprints (z / f mm each).

    r: the relative RMS residual of the pattern model at a depth (`pattern_model.photometric_residual`; patterns as
    rendered), r_own at the pixel's depth and r_across the lowest over the depths across. The pixel keeps its depth
    where r_own <= margin r_across, takes the depth of that lowest where r_across <= margin r_own, and is dropped
    where neither explains its codes that much better (margin < 1; 0.5: one residual at most half the other).
    Comparing two depths instead of searching the whole ray keeps chance matches rare: with 6 codes, a search of
    the ray finds another depth that fits as well on about a quarter of the pixels (extraction.confidence,
    `uniqueness`). Cost: one residual at the edge pixels per window offset (24 for radius 2)."""
    d = np.asarray(depth, np.float32)
    out = d.copy()
    none = np.zeros(d.shape, bool)
    if radius <= 0 or not np.isfinite(d).any():
        return out, none, none.copy()
    H, W = d.shape
    limit = footprints * d / min(inputs.camera.fx, inputs.camera.fy)
    pad = np.pad(d, radius, constant_values=np.nan)
    offsets = _window_offsets(radius)

    # one offset at a time: the depths across a jump (NaN where none, or NaN on either side) and their residuals;
    # the edge pixels are those with a depth across at some offset
    edge = np.zeros(d.shape, bool)
    best = np.full(d.shape, np.inf, np.float32)
    best_depth = np.full(d.shape, np.nan, np.float32)
    for dy, dx in offsets:
        n = pad[radius + dy : radius + dy + H, radius + dx : radius + dx + W]
        with np.errstate(invalid="ignore"):
            candidate = np.where(np.abs(n - d) > limit, n, np.nan).astype(np.float32)
        found = np.isfinite(candidate)
        if not found.any():
            continue
        edge |= found
        r = np.nan_to_num(photometric_residual(candidate, *inputs.model), nan=np.inf)
        lower = r < best
        best = np.where(lower, r, best)
        best_depth = np.where(lower, candidate, best_depth)
    if not edge.any():
        return out, none, none.copy()
    r_own = np.nan_to_num(photometric_residual(np.where(edge, d, np.nan).astype(np.float32), *inputs.model),
                          nan=np.inf)
    switched = edge & np.isfinite(best) & (best <= margin * r_own)
    dropped = edge & ~switched & ~(r_own <= margin * best)
    out[switched] = best_depth[switched]
    out[dropped] = np.nan
    return out, switched, dropped
