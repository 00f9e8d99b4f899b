"""Depth by exhaustive search along each camera ray (any pattern set), the neural SDF's starting point.

The photometric loss of the paper's method is far from convex in depth: with random binary squares,
any depth more than about one square away from the truth sits in another local minimum, and the NeuS
sphere initialisation is hundreds of mm from a wall at the back of the working volume. `search_depth`
finds, for every `stride`-th pixel, the camera depth whose predicted intensities a + b P_n(pi(x)) best
match the observations over a small window (the window's pixels share the hypothesis depth), keeps the
confident answers (the best cost clearly below the best cost elsewhere on the ray), and spreads them to
full resolution. The trainer's warm-up pulls the rendered depth onto this map before the paper's losses
take over.
"""
from __future__ import annotations

import time

import numpy as np

from ..devices import warp_device
from .pattern_model import lit_with_contrast, offset_and_modulation
from slwarp.kernels import runtime
from slwarp.kernels.geometry import projector_params
from slwarp.kernels.search import search_kernel


def search_depth(camera, projector, images, patterns, depth_range, *, valid=None, step_mm: float = 1.0,
                 max_hypotheses: int = 1024, radius: int = 2, stride: int = 2, ratio: float = 0.8,
                 exclude_mm: float = 6.0, device=None) -> tuple[np.ndarray, dict]:
    """Depth map [H, W] (camera z, mm; NaN where not confident) and info (timings, counts).

    images [N, H, W], patterns [N, Hp, Wp] in [0, 1]; valid [H, W]: the pixels to search (default: those lit
    with contrast, `pattern_model.lit_with_contrast`). Hypotheses every `step_mm` (at most `max_hypotheses`) between the near and far depth.
    A pixel is confident when its best cost < `ratio` x the best cost farther than `exclude_mm` away.
    device: a torch device or device string (None: auto).
    """
    wp = runtime.init()
    device = warp_device(device)
    t0 = time.perf_counter()
    images = np.asarray(images, np.float32)
    N, H, W = images.shape
    a, b = offset_and_modulation(images)
    if valid is None:
        valid = lit_with_contrast(b)
    near, far = (float(x) for x in depth_range)
    n_hyp = int(min(max_hypotheses, max(16, np.ceil((far - near) / step_mm))))
    rays = camera.pixel_to_ray(camera.pixel_grid()).astype(np.float32)
    hs, ws = (H + stride - 1) // stride, (W + stride - 1) // stride
    kernel = search_kernel(int(N))
    with wp.ScopedDevice(device):
        depth = wp.empty((hs, ws), dtype=float)
        best = wp.empty((hs, ws), dtype=float)
        second = wp.empty((hs, ws), dtype=float)
        wp.launch(kernel, dim=(hs, ws), inputs=[
            wp.array(rays, dtype=wp.vec3), wp.array(np.ascontiguousarray(images.transpose(1, 2, 0))),
            wp.array(a), wp.array(b), wp.array(valid.astype(np.int32)),
            wp.array(np.ascontiguousarray(np.asarray(patterns, np.float32).transpose(1, 2, 0))),
            projector_params(projector), near, far, n_hyp, int(radius), int(stride),
            int(np.ceil(exclude_mm / ((far - near) / n_hyp))),
        ], outputs=[depth, best, second])
        d, c1, c2 = depth.numpy(), best.numpy(), second.numpy()
    t1 = time.perf_counter()
    confident = np.isfinite(d) & (c1 < ratio * c2)
    coarse = np.where(confident, d, np.nan)
    coarse = _median3(coarse)
    full = np.repeat(np.repeat(coarse, stride, axis=0), stride, axis=1)[:H, :W]
    full[~valid] = np.nan
    info = {"hypotheses": n_hyp, "step_mm": (far - near) / n_hyp, "stride": stride, "radius": radius,
            "confident_share": float(confident[np.isfinite(d)].mean()) if np.isfinite(d).any() else 0.0,
            "search_s": t1 - t0, "total_s": time.perf_counter() - t0, "device": device}
    return full.astype(np.float32), info


def _median3(x: np.ndarray) -> np.ndarray:
    """3x3 median ignoring NaN (a cell keeps NaN when it was NaN): removes isolated wrong answers."""
    H, W = x.shape
    pad = np.pad(x, 1, constant_values=np.nan)
    stack = np.stack([pad[dy : dy + H, dx : dx + W] for dy in range(3) for dx in range(3)])
    with np.errstate(all="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.nanmedian(stack, axis=0)
    # a value far from its neighbourhood's median is an outlier
    out = np.where(np.abs(x - med) < 10.0, x, np.nan)
    return out
