"""Helpers on depth maps [H, W] (camera z, mm; NaN: no depth) that the depth search, the training's start and the
extraction share: the pixels' 8 neighbours (`neighbour_stack`, `neighbours_at`, `neighbours_within`), the connected
groups of one surface (`component_sizes`, with `AGREE_MM`), maps of values on the pixels with depth (`on_depth`) and
the back-projection to points (`depth_to_points`).
"""
from __future__ import annotations

import numpy as np
import torch

from ..scans.scanner import camera_rays

__all__ = ["AGREE_MM", "component_sizes", "neighbour_stack", "neighbours_at", "neighbours_within", "on_depth",
           "depth_to_points"]


# the 3x3 and 5x5 searches "agree" within this (mm); two depths of one surface agree within it (the surface term's
# groups, the extraction's repair and fill)
AGREE_MM = 3.0


def component_sizes(depth: np.ndarray, tol_mm: float) -> np.ndarray:
    """[H, W] int: the pixel count of each finite pixel's connected group, where two of the 8 neighbours connect
    when their depths differ by less than tol_mm (0 where depth is NaN).

    Exact, in two steps. The row and column links are labelled by OpenCV on a doubled grid: pixel (y, x) at
    (2y, 2x), its link to the right at (2y, 2x + 1) and down at (2y + 1, 2x), cell centres empty, so that 4-connected
    labelling joins exactly the linked pixels. The diagonal links, which would cross on that grid, then merge
    those labels with a union-find over the labels they join (few: on a surface nearly every diagonal pair is
    already joined through a row and a column). 0.10 s at 1280 x 1024 against 0.84 s for a union-find over
    the pixels (bench/residual_speed.py, CPU)."""
    import cv2

    d = np.asarray(depth, np.float64)
    H, W = d.shape
    finite = np.isfinite(d)
    with np.errstate(invalid="ignore"):
        right = np.abs(d[:, 1:] - d[:, :-1]) < tol_mm  # [H, W-1]; NaN compares False
        down = np.abs(d[1:, :] - d[:-1, :]) < tol_mm  # [H-1, W]
        diag = np.abs(d[1:, 1:] - d[:-1, :-1]) < tol_mm  # (y, x) - (y+1, x+1), [H-1, W-1]
        anti = np.abs(d[1:, :-1] - d[:-1, 1:]) < tol_mm  # (y, x+1) - (y+1, x), [H-1, W-1]
    grid = np.zeros((2 * H - 1, 2 * W - 1), np.uint8)
    grid[::2, ::2] = finite
    grid[::2, 1::2] = right
    grid[1::2, ::2] = down
    n_labels, labels = cv2.connectedComponents(grid, connectivity=4, ltype=cv2.CV_32S)
    label = labels[::2, ::2]  # [H, W], 0 where NaN
    # the diagonal links between different labels, each pair once (selected before they are gathered: nearly all
    # diagonal links join pixels of one label already)
    la, lb, lc, ld = label[:-1, :-1], label[1:, 1:], label[:-1, 1:], label[1:, :-1]
    cross, cross_anti = diag & (la != lb), anti & (lc != ld)
    pairs = np.concatenate([np.stack([la[cross], lb[cross]], 1), np.stack([lc[cross_anti], ld[cross_anti]], 1)])
    parent = np.arange(n_labels)
    if len(pairs):
        a, b = np.unique(np.sort(pairs, 1), axis=0).T
        while True:  # hang each pair's larger root under its smaller until both share one
            ra, rb = _roots(parent, a), _roots(parent, b)
            diff = ra != rb
            if not diff.any():
                break
            parent[np.maximum(ra[diff], rb[diff])] = np.minimum(ra[diff], rb[diff])
            a, b = a[diff], b[diff]
    group = _roots(parent, np.arange(n_labels))[label[finite]]  # each finite pixel's merged label
    out = np.zeros((H, W), np.int64)
    out[finite] = np.bincount(group, minlength=n_labels)[group]
    return out


def _roots(parent: np.ndarray, i: np.ndarray) -> np.ndarray:
    """The union-find roots of the nodes i (parent: [n], halving the paths on the way)."""
    while True:
        p = parent[i]
        if np.array_equal(p, parent[p]):
            return p
        parent[i] = parent[p]
        i = parent[i]


# the 8 neighbours as (dy, dx) into the map padded by one pixel, in the order of neighbour_stack's rows
_NEIGHBOURS = tuple((dy, dx) for dy in range(3) for dx in range(3) if (dy, dx) != (1, 1))
# the same as offsets (dy, dx) from the pixel
NEIGHBOUR_OFFSETS = tuple((dy - 1, dx - 1) for dy, dx in _NEIGHBOURS)


def neighbour_stack(depth):
    """[8, H, W] float64: each pixel's 8 neighbours' depths (NaN outside the image); depth [H, W] numpy, or a
    tensor (a tensor back, on its device)."""
    if isinstance(depth, torch.Tensor):
        d = depth.double()
        H, W = d.shape
        pad = torch.nn.functional.pad(d, (1, 1, 1, 1), value=float("nan"))
        return torch.stack([pad[dy : dy + H, dx : dx + W] for dy, dx in _NEIGHBOURS])
    d = np.asarray(depth, np.float64)
    H, W = d.shape
    pad = np.pad(d, 1, constant_values=np.nan)
    return np.stack([pad[dy : dy + H, dx : dx + W] for dy, dx in _NEIGHBOURS])


def neighbours_at(depth: np.ndarray, index: np.ndarray) -> np.ndarray:
    """[8, P] float64: neighbour_stack at the pixels of flat indices index [P] only."""
    d = np.asarray(depth, np.float64)
    pad = np.pad(d, 1, constant_values=np.nan)
    y, x = np.divmod(np.asarray(index), d.shape[1])
    return np.stack([pad[y + dy, x + dx] for dy, dx in _NEIGHBOURS])


def neighbours_within(depth: np.ndarray, tol_mm: float, index: np.ndarray | None = None,
                      device=None) -> np.ndarray:
    """[H, W] int: how many of each pixel's 8 neighbours have a depth within tol_mm of its own (computed by torch
    on `device`, default the CPU); with index (flat pixel indices [P]) the same counts [P] at those pixels only."""
    if index is None:
        d = torch.as_tensor(np.asarray(depth, np.float64), device=device)
        return (torch.abs(neighbour_stack(d) - d) < tol_mm).sum(0).int().cpu().numpy()
    own = np.asarray(depth, np.float64).reshape(-1)[index]
    with np.errstate(invalid="ignore"):
        return (np.abs(neighbours_at(depth, index) - own) < tol_mm).sum(0).astype(np.int32)


def on_depth(values: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """values as float32 in [0, 1], NaN where depth is NaN."""
    return np.where(np.isfinite(depth), np.clip(values, 0.0, 1.0), np.nan).astype(np.float32)


def depth_to_points(depth: np.ndarray, camera) -> np.ndarray:
    """[P, 3] camera-frame points (mm) of the finite pixels of a depth map (z = depth). The rays are gathered once
    (twice took 0.10 s at 1280 x 1024 on the CPU, once 0.05 s: a scan's time in a batch)."""
    d = camera_rays(camera)
    ok = np.isfinite(depth)
    rays = d[ok]
    return (rays * (depth[ok] / rays[:, 2])[:, None]).astype(np.float32)
