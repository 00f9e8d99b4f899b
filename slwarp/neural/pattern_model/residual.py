"""The photometric residual of a depth map (how much of each pixel's modulation the codes predicted at its depth
leave unexplained), on the host or on a device; the photometric filter and the photometric confidence built on it,
which the training (its surface term) and the extraction share.

`photometric_confidence`: 1 - r, r the relative RMS residual of the pattern model at the pixel's depth
(`photometric_residual`), a map [H, W] float32 in [0, 1], NaN where the depth map has no depth. The other confidence
terms, and the confidence map an extraction writes, are in `slwarp.neural.extraction.confidence`.
"""
from __future__ import annotations

import numpy as np
import torch

from ...scans.scanner import bounded_cache, camera_rays
from ..depth_maps import on_depth
from ..ops.twin import bilinear_patterns
from .image import (MIN_MODULATION, OFF_IMAGE_PX, offset_and_modulation, predicted_intensities, projector_coords_of,
                    sample_patterns_at)

__all__ = ["SPARSE_SHARE", "photometric_residual", "residual_at", "photometric_filter", "photometric_confidence"]


# below this share of pixels with depth, photometric_residual works on those pixels only (the same values): the
# extraction asks it about a few candidates at a time (the repair's changes, its growth, the edge readmission)
SPARSE_SHARE = 0.25


def _relative_rms(images, a, b, pred):
    """RMS over the frames (axis 0) of images - a - b pred, over max(b, MIN_MODULATION)."""
    return np.sqrt(np.mean((images - a - b * pred) ** 2, axis=0)) / np.maximum(b, MIN_MODULATION)


def _host_residual_at(index: np.ndarray, depths: np.ndarray, camera, projector, images: np.ndarray,
                      patterns: np.ndarray) -> np.ndarray:
    """[P] float32: the residual of the pixels at flat indices `index` [P] at `depths` [P] mm (finite), on the host
    (the dense path's arithmetic per pixel)."""
    obs = images.reshape(len(images), -1)[:, index]  # [N, P]
    a, b = offset_and_modulation(obs)
    pred = sample_patterns_at(patterns, projector_coords_of(index, depths, camera, projector))
    return _relative_rms(obs, a, b, pred).astype(np.float32)


def _sparse_residual(depth: np.ndarray, camera, projector, images: np.ndarray, patterns: np.ndarray) -> np.ndarray:
    """photometric_residual computed at the finite pixels of depth only (the same arithmetic per pixel)."""
    out = np.full(depth.shape, np.nan, np.float32)
    index = np.flatnonzero(np.isfinite(depth))
    if index.size:
        out.reshape(-1)[index] = _host_residual_at(index, np.asarray(depth).reshape(-1)[index], camera, projector,
                                                   images, patterns)
    return out


# each camera's unit rays [H*W, 3] float64 on a device (the last few), for _residual_on_device
_DEVICE_RAYS: dict = {}


def _rays_on(camera, device) -> torch.Tensor:
    """camera_rays(camera) as a [H*W, 3] float64 tensor on `device`, uploaded once per camera and device."""
    # a copy: camera_rays' cached grid is read-only
    return bounded_cache(_DEVICE_RAYS, camera.cache_key + (str(device),),
                   lambda: torch.from_numpy(np.array(camera_rays(camera).reshape(-1, 3), np.float64)).to(device))


def _residual_on_device(depth: np.ndarray, camera, projector, images, patterns: torch.Tensor) -> np.ndarray:
    """photometric_residual at the finite pixels of depth, on the device of patterns (a tensor; images numpy or a
    tensor [N, H, W]): the host path's arithmetic in the same order (projection in float64, the RMS summed frame
    by frame in float32), the sampling the torch twin's (`twin.bilinear_patterns`, OpenCV 5's cv2.remap within
    2e-7, a float's rounding; OpenCV 4 rounds the coordinates to 1/32 px first). 0.03 s a call on the host at 1280 x 1024, ten to
    twenty calls per GPU extraction."""
    dev = patterns.device
    flat = torch.as_tensor(np.asarray(depth, np.float32).reshape(-1), device=dev)
    out = torch.full_like(flat, float("nan"))
    idx = torch.nonzero(torch.isfinite(flat)).squeeze(1)
    if idx.numel():
        out[idx] = _device_residual_at(idx, flat[idx], camera, projector, images, patterns)
    return out.reshape(np.shape(depth)).cpu().numpy()


def _device_residual_at(idx: torch.Tensor, depths: torch.Tensor, camera, projector, images,
                        patterns: torch.Tensor) -> torch.Tensor:
    """[P] float32 on the device of patterns: the residual of the pixels at flat indices idx [P] (long, there) at
    depths [P] mm (float32, there, finite); `_residual_on_device`'s arithmetic per pixel."""
    dev = patterns.device
    rays = _rays_on(camera, dev)[idx]
    uv = projector.project_camera_points(rays * (depths.double() / rays[:, 2])[:, None])
    uv = torch.where(torch.isfinite(uv), uv, torch.full_like(uv, OFF_IMAGE_PX)).float()
    pred = bilinear_patterns(patterns.float(), uv).t()  # [N, P]
    obs = torch.as_tensor(images, dtype=torch.float32, device=dev).reshape(len(pred), -1)[:, idx]  # [N, P]
    a, b = offset_and_modulation(obs)
    diff = obs - a - b * pred
    total = diff[0] * diff[0]
    for k in range(1, len(diff)):  # frame by frame, as numpy sums an axis-0 mean
        total = total + diff[k] * diff[k]
    return torch.sqrt(total / len(diff)) / torch.clamp(b, min=MIN_MODULATION)


def residual_at(index: torch.Tensor, depths: torch.Tensor, camera, projector, images, patterns) -> torch.Tensor:
    """[P] float32 on the device of `index`: `photometric_residual` of the pixels at flat indices index [P] (long;
    repeats allowed) at depths [P] mm (finite), the same value per pixel and depth as a map would give. One call
    for several depths per pixel (extraction.edges: the depths across an edge). Computed on the device of patterns
    when they are a tensor, else on the host."""
    if isinstance(patterns, torch.Tensor):
        dev = patterns.device
        return _device_residual_at(index.to(dev), depths.to(dev, torch.float32), camera, projector, images,
                                   patterns).to(index.device)
    r = _host_residual_at(index.cpu().numpy(), depths.cpu().numpy().astype(np.float32), camera, projector,
                          np.asarray(images, np.float32), patterns)
    return torch.from_numpy(r).to(index.device)


def photometric_residual(depth: np.ndarray, camera, projector, images, patterns) -> np.ndarray:
    """[H, W]: RMS over the frames of I - (a + b P(pi(x))), relative to the pixel's modulation b (a, b as in
    `offset_and_modulation`); NaN where depth is NaN. patterns as rendered (blurred). images [N, H, W] and patterns
    [N, Hp, Wp] numpy (computed on the host; a map with depth at fewer than SPARSE_SHARE of its pixels at those
    pixels only), or patterns a tensor: computed on its device (`_residual_on_device`; the extraction on a GPU)."""
    if isinstance(patterns, torch.Tensor):
        return _residual_on_device(np.asarray(depth), camera, projector, images, patterns)
    images = np.asarray(images, np.float32)
    if np.isfinite(depth).mean() < SPARSE_SHARE:
        return _sparse_residual(np.asarray(depth), camera, projector, images, patterns)
    a, b = offset_and_modulation(images)
    r = _relative_rms(images, a, b, predicted_intensities(depth, camera, projector, patterns))
    return np.where(np.isfinite(depth), r, np.nan).astype(np.float32)


def photometric_filter(depth: np.ndarray, camera, projector, images: np.ndarray, patterns: np.ndarray,
                       threshold: float = 0.4) -> np.ndarray:
    """Depth with the pixels whose predicted intensities disagree with the images removed (NaN).

    At an occlusion edge a smooth field can leave a pixel or two on the wrong side's surface; there the
    random binary codes predicted from the depth do not match what the pixel saw. Pixels whose relative RMS
    residual (`photometric_residual`) is at or above `threshold` are dropped (measured on the small-rig
    bunny: correct pixels have a 99th percentile of 0.39, pixels off by more than 20 mm a 10th of 0.47).
    """
    r = photometric_residual(depth, camera, projector, images, patterns)
    return np.where(r < threshold, depth, np.nan).astype(np.float32)


def photometric_confidence(depth: np.ndarray, camera, projector, images, patterns) -> np.ndarray:
    """[H, W]: 1 - relative RMS residual of the pattern model at depth (mm; NaN invalid). images [N, H, W],
    patterns [N, Hp, Wp] as rendered (blurred): numpy, or tensors on the device to compute on
    (`photometric_residual`)."""
    return on_depth(1.0 - photometric_residual(depth, camera, projector, images, patterns), depth)
