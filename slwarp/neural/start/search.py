"""Depth by exhaustive search along each camera ray (any pattern set), the neural SDF's starting point.

The photometric loss of the paper's method is far from convex in depth: with random binary squares,
any depth more than about one square away from the truth sits in another local minimum, and the NeuS
sphere initialisation is hundreds of mm from a wall at the back of the working volume. `search_depth`
finds, for every `stride`-th pixel, the camera depth whose predicted intensities a + b P_n(pi(x)) best
match the observations over a small window (the window's pixels share the hypothesis depth), keeps the
confident answers (the best cost clearly below the best cost elsewhere on the ray), and spreads them to
full resolution. The trainer's warm-up pulls the rendered depth onto this map before the paper's losses
take over. The extraction's search repair runs the same search per pixel (slwarp.neural.extraction.repair);
`depth_maps.component_sizes` groups the depths of one surface for both.
"""
from __future__ import annotations

import time

import cv2
import numpy as np
import torch

from ...devices import warp_device
from ...scans.scanner import camera_rays
from ..pattern_model import lit_with_contrast, offset_and_modulation
from slwarp.kernels import runtime
from slwarp.kernels.geometry import projector_params
from slwarp.kernels.search import NO_COST, search_kernels


# values of one block of per-pixel costs [hypotheses, H, W] (128 MB of float32; `search_depth`)
SEARCH_BLOCK_VALUES = 1 << 25


def search_depth(camera, projector, images, patterns, depth_range, *, valid=None, step_mm: float = 1.0,
                 max_hypotheses: int = 1024, radius: int = 2, window_step: int = 1, stride: int = 2,
                 ratio: float = 0.8, exclude_mm: float = 6.0, centres=None, median: bool = True, device=None) -> tuple[np.ndarray, dict]:
    """Depth map [H, W] (camera z, mm; NaN where not confident) and info (timings, counts).

    images [N, H, W], patterns [N, Hp, Wp] in [0, 1] (numpy, or tensors on `device`); valid [H, W]: the pixels to search and that the windows
    count (default: those lit with contrast, `pattern_model.lit_with_contrast`); centres [H, W] (default: valid):
    the pixels to search when only some are wanted. Hypotheses every `step_mm` (at most `max_hypotheses`)
    between the near and far depth; windows of (2 radius + 1)^2 pixels `window_step` camera px apart (a designed
    pattern set's, `design.DesignOptions.window_step`). A pixel is confident when its best cost < `ratio` x the best
    cost farther than `exclude_mm` away. median: drop answers > 10 mm from their 3x3 neighbourhood's median.
    device: a torch device or device string (None: auto).
    """
    wp = runtime.init()
    device = warp_device(device)
    t0 = time.perf_counter()
    if not isinstance(images, torch.Tensor):
        images = np.asarray(images, np.float32)
    N, H, W = images.shape
    a, b = offset_and_modulation(images)
    if valid is None:
        valid = lit_with_contrast(b)
    valid = valid.cpu().numpy() if isinstance(valid, torch.Tensor) else np.asarray(valid, bool)
    near, far = (float(x) for x in depth_range)
    n_hyp = int(min(max_hypotheses, max(16, np.ceil((far - near) / step_mm))))
    rays = camera_rays(camera).astype(np.float32)
    hs, ws = (H + stride - 1) // stride, (W + stride - 1) // stride
    pixel_costs, window_search, finish = search_kernels(int(N))
    searched = np.zeros((H, W), bool)  # the centres the windows sit on
    searched[::stride, ::stride] = (valid if centres is None else np.asarray(centres, bool) & valid)[::stride, ::stride]
    # the pixels whose own costs some searched window sums
    k = 2 * int(radius) * int(window_step) + 1
    needed = cv2.dilate(searched.astype(np.uint8), np.ones((k, k), np.uint8)).astype(bool) & valid
    block = int(max(1, min(n_hyp, SEARCH_BLOCK_VALUES // (H * W))))
    with wp.ScopedDevice(device):
        depth = wp.empty((hs, ws), dtype=float)
        best = wp.full((hs, ws), NO_COST, dtype=float)
        best_h = wp.full((hs, ws), -1, dtype=wp.int32)
        second = wp.full((hs, ws), NO_COST, dtype=float)
        cost = wp.empty((block, H, W), dtype=float)
        rays_w, obs_w = wp.array(rays, dtype=wp.vec3), _warp_array(_frames_last(images))
        a_w, b_w, pat_w = _warp_array(a), _warp_array(b), _warp_array(_frames_last(patterns))
        valid_w, needed_w = wp.array(valid.astype(np.int32)), wp.array(needed.astype(np.int32))
        centre_w = wp.array(searched.astype(np.int32))
        prm = projector_params(projector)
        exclude = int(np.ceil(exclude_mm / ((far - near) / n_hyp)))
        for h0 in range(0, n_hyp, block):
            wp.launch(pixel_costs, dim=(block, H, W), inputs=[rays_w, obs_w, a_w, b_w, needed_w, pat_w, prm, near, far,
                                                             n_hyp, h0], outputs=[cost])
            wp.launch(window_search, dim=(hs, ws), inputs=[cost, valid_w, centre_w, n_hyp, h0, int(radius),
                                                          int(window_step), int(stride), exclude],
                      outputs=[best, best_h, second])
        wp.launch(finish, dim=(hs, ws), inputs=[best_h, near, far, n_hyp], outputs=[best, second, depth])
        # the answers' confidence, outlier rule and spreading on the search's device (a full-resolution map's
        # 3x3 median took 0.25 s on the host, twice per search repair)
        d, c1, c2 = wp.to_torch(depth), wp.to_torch(best), wp.to_torch(second)
        found = torch.isfinite(d)
        confident = found & (c1 < ratio * c2)
        coarse = torch.where(confident, d, torch.full_like(d, float("nan")))
        if median:
            coarse = _median3(coarse)
        full = coarse.repeat_interleave(stride, 0).repeat_interleave(stride, 1)[:H, :W]
        full = torch.where(torch.as_tensor(valid, device=full.device), full, torch.full_like(full, float("nan")))
        full = full.cpu().numpy().astype(np.float32)  # a copy: the Warp arrays go with this block
        share = float(confident[found].double().mean()) if bool(found.any()) else 0.0
    t1 = time.perf_counter()
    info = {"hypotheses": n_hyp, "step_mm": (far - near) / n_hyp, "stride": stride, "radius": radius,
            "window_step": window_step, "confident_share": share, "search_s": t1 - t0, "total_s": time.perf_counter() - t0, "device": device}
    return full, info


def _frames_last(x):
    """[N, H, W] numpy or tensor -> [H, W, N] float32 of the same kind."""
    if isinstance(x, torch.Tensor):
        return x.float().permute(1, 2, 0)
    return np.asarray(x, np.float32).transpose(1, 2, 0)


def _warp_array(x):
    """A Warp array of a numpy array (copied to the launch's device) or of a tensor on that device (shared)."""
    wp = runtime.init()
    if isinstance(x, torch.Tensor):
        return wp.from_torch(x.contiguous())
    return wp.array(np.ascontiguousarray(x))


def _median3(x):
    """x [H, W] (numpy or torch, the same kind back) without the values more than 10 mm from their 3x3
    neighbourhood's median, NaN ignored (a cell keeps NaN when it was NaN): removes isolated wrong answers.

    The median as np.nanmedian takes it (the mean of the two middle values of an even count), from one sort of
    each pixel's 9 values with the NaNs last, in x's precision and on x's device (CPU: 0.25 s at 1280 x 1024
    against 0.72 s for np.nanmedian, bench/residual_speed.py)."""
    if not isinstance(x, torch.Tensor):
        return _median3(torch.from_numpy(np.ascontiguousarray(x))).numpy()
    H, W = x.shape
    pad = torch.nn.functional.pad(x, (1, 1, 1, 1), value=float("nan"))
    stack = torch.stack([pad[dy : dy + H, dx : dx + W] for dy in range(3) for dx in range(3)])  # [9, H, W]
    stack = torch.sort(stack, dim=0).values  # NaN sorts last, so the finite values come first in order
    count = torch.isfinite(stack).sum(0)
    lo = torch.gather(stack, 0, (torch.clamp(count - 1, min=0) // 2)[None])[0]
    hi = torch.gather(stack, 0, (count // 2)[None])[0]
    nan = torch.full_like(x, float("nan"))
    med = torch.where(count > 0, 0.5 * (lo + hi), nan)
    # a value far from its neighbourhood's median is an outlier
    return torch.where(torch.abs(x - med) < 10.0, x, nan)
