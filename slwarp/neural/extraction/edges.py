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
import torch

from ..pattern_model import residual_at
from .state import ModelInputs

__all__ = ["settle_edge_sides"]


def _window_offsets(radius: int) -> list[tuple[int, int]]:
    return [(dy, dx) for dy in range(-radius, radius + 1) for dx in range(-radius, radius + 1) if (dy, dx) != (0, 0)]


def settle_edge_sides(depth: np.ndarray, inputs: ModelInputs, radius: int, margin: float,
                      footprints: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(depth [H, W] mm, switched [H, W] bool, dropped [H, W] bool) after settling each pixel with a depth across an
    edge: a pixel of its (2 radius + 1)^2 window whose depth differs from its own by more than `footprints` pixel
    footprints (z / f mm each).

    r: the relative RMS residual of the pattern model at a depth (`pattern_model.residual_at`; patterns as rendered),
    r_own at the pixel's depth and r_across the lowest over the depths across (the first window offset on a tie). The
    pixel keeps its depth where r_own <= margin r_across, takes the depth of that lowest where r_across <= margin
    r_own, and is dropped where neither explains its codes that much better (margin < 1; 0.5: one residual at most
    half the other). Comparing two depths instead of searching the whole ray keeps chance matches rare: with 6 codes,
    a search of the ray finds another depth that fits as well on about a quarter of the pixels (extraction.confidence,
    `uniqueness`). Runs where the model's patterns are (a GPU's extraction: there), every (pixel, depth across) pair
    and the edge pixels' own depths in one residual call: a residual map per window offset, on the host, took 0.2 s
    of a 1280 x 1024 extraction (H100, cProfile)."""
    d = np.asarray(depth, np.float32)
    out = d.copy()
    none = np.zeros(d.shape, bool)
    if radius <= 0 or not np.isfinite(d).any():
        return out, none, none.copy()
    dev = inputs.patterns.device if isinstance(inputs.patterns, torch.Tensor) else torch.device("cpu")
    H, W = d.shape
    flat = torch.as_tensor(d, device=dev).reshape(-1)
    limit = footprints * flat / min(inputs.camera.fx, inputs.camera.fy)
    pad = torch.nn.functional.pad(flat.reshape(1, 1, H, W), (radius,) * 4, value=float("nan"))[0, 0]

    # the (pixel, depth across) pairs, offset after offset: a neighbour more than the limit away (NaN on either side
    # never is); the edge pixels are those with a pair
    pixels, across = [], []
    for dy, dx in _window_offsets(radius):
        n = pad[radius + dy : radius + dy + H, radius + dx : radius + dx + W].reshape(-1)
        idx = torch.nonzero((n - flat).abs() > limit).squeeze(1)
        pixels.append(idx)
        across.append(n[idx])
    pix, across = torch.cat(pixels), torch.cat(across)
    if pix.numel() == 0:
        return out, none, none.copy()
    edge = torch.unique(pix)  # sorted
    r = torch.nan_to_num(residual_at(torch.cat([pix, edge]), torch.cat([across, flat[edge]]), *inputs.model),
                         nan=float("inf"))
    r_across, r_own = r[: pix.numel()], r[pix.numel():]
    # per edge pixel the lowest residual across, the earliest offset on a tie: stable sorts by residual, then pixel
    k = torch.sort(r_across, stable=True).indices
    k = k[torch.sort(pix[k], stable=True).indices]
    first = torch.ones(k.numel(), dtype=torch.bool, device=dev)
    first[1:] = pix[k[1:]] != pix[k[:-1]]
    k = k[first]  # one pair per edge pixel, in the order of `edge`
    best, best_depth = r_across[k], across[k]
    switched = torch.isfinite(best) & (best <= margin * r_own)
    dropped = ~switched & ~(r_own <= margin * best)
    sw, dr = edge[switched].cpu().numpy(), edge[dropped].cpu().numpy()
    out.reshape(-1)[sw] = best_depth[switched].cpu().numpy()
    out.reshape(-1)[dr] = np.nan
    switched_map, dropped_map = none.copy(), none.copy()
    switched_map.reshape(-1)[sw] = True
    dropped_map.reshape(-1)[dr] = True
    return out, switched_map, dropped_map
