"""The image model I_i(r) = a(r) + b(r) P_i(pi(x)) on the host (numpy, OpenCV) and the pattern blur (torch): the offset
and modulation (min/max over the frames, or by least squares against the codes), the contrast test, the blur, the
projector coordinates of a depth map and the patterns sampled there.
"""
from __future__ import annotations

import numpy as np
import torch

from ...scans.scanner import camera_rays, with_halo  # with_halo: the lens model the simulator shares
from ..config import CONTRAST_THRESHOLD  # the config holds the default; re-exported for the renderer

__all__ = [
    "CONTRAST_THRESHOLD",
    "OFF_IMAGE_PX",
    "MIN_MODULATION",
    "LS_RIDGE",
    "offset_and_modulation",
    "lit_with_contrast",
    "blur_patterns",
    "with_halo",
    "projector_coords",
    "projector_coords_at",
    "projector_coords_of",
    "sample_patterns",
    "sample_patterns_at",
    "predicted_intensities",
    "least_squares_residual",
    "least_squares_offset_modulation",
]

# projector pixel given to pixels without depth: off the image, so every pattern samples 0 there
OFF_IMAGE_PX = -10.0
# floor of the modulation b that the photometric residual is divided by (unlit pixels stay finite)
MIN_MODULATION = 1.0e-3
# least-squares offset/modulation: ridge pulling b toward max - min, in units of the codes' variance over the
# frames (it only matters where the codes barely vary, e.g. a point off the projector image)
LS_RIDGE = 0.02


def offset_and_modulation(images):
    """(a, b): a = min_i I_i, b = max_i I_i - a over the frames of images [N, ...] (numpy or torch, the
    same kind back; numpy in float32)."""
    if isinstance(images, torch.Tensor):
        lo = images.min(dim=0).values
        return lo, images.max(dim=0).values - lo
    images = np.asarray(images, np.float32)
    lo = images.min(0)
    return lo, images.max(0) - lo


def lit_with_contrast(modulation, threshold: float = CONTRAST_THRESHOLD):
    """Boolean mask of the pixels whose modulation b exceeds `threshold` (numpy or torch)."""
    return modulation > threshold


def blur_patterns(patterns: torch.Tensor, sigma: float) -> torch.Tensor:
    """patterns [N, Hp, Wp] Gaussian-blurred by `sigma` projector px (separable, truncated at 3 sigma, edge
    values replicated); sigma <= 0 returns the patterns themselves."""
    if sigma <= 0:
        return patterns
    r = int(np.ceil(3.0 * sigma))
    x = torch.arange(-r, r + 1, dtype=torch.float32, device=patterns.device)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    k = k / k.sum()
    # taps summed as shifted slices, not conv2d: a fresh process's first conv2d on a GPU starts cuDNN, about 0.1 s of
    # the set-up for the only convolution of a run (H100 host, cProfile)
    p = torch.nn.functional.pad(patterns[:, None], (r, r, 0, 0), mode="replicate")[:, 0]
    W = patterns.shape[-1]
    p = sum(k[j] * p[..., j: j + W] for j in range(2 * r + 1))
    p = torch.nn.functional.pad(p[:, None], (0, 0, r, r), mode="replicate")[:, 0]
    H = patterns.shape[-2]
    return sum(k[j] * p[..., j: j + H, :] for j in range(2 * r + 1)).contiguous()


def _project_rays(rays: np.ndarray, depth: np.ndarray, projector) -> np.ndarray:
    """[..., 2] float32 projector pixels of the points at camera depth `depth` [...] (mm) on unit camera rays
    [..., 3]; OFF_IMAGE_PX where the depth is NaN or the point does not project."""
    with np.errstate(invalid="ignore"):
        X = rays * (np.asarray(depth, np.float64) / rays[..., 2])[..., None]
        uv = np.asarray(projector.project_camera_points(X.reshape(-1, 3)), np.float64).reshape(X.shape[:-1] + (2,))
    return np.where(np.isfinite(uv), uv, OFF_IMAGE_PX).astype(np.float32)


def projector_coords(depth: np.ndarray, camera, projector) -> np.ndarray:
    """[H, W, 2] float32 projector pixel where each pixel's depth point (camera z, mm) projects;
    OFF_IMAGE_PX where depth is NaN or the point does not project."""
    return _project_rays(camera_rays(camera), depth, projector)


def projector_coords_at(index: np.ndarray, depth: np.ndarray, camera, projector) -> np.ndarray:
    """[P, 2] projector_coords of the pixels at flat indices `index` [P] of the depth map [H, W] only."""
    return projector_coords_of(index, np.asarray(depth).reshape(-1)[index], camera, projector)


def projector_coords_of(index: np.ndarray, depths: np.ndarray, camera, projector) -> np.ndarray:
    """[P, 2] projector pixels of the camera pixels at flat indices `index` [P] (repeats allowed) at depths [P] mm."""
    return _project_rays(camera_rays(camera).reshape(-1, 3)[index], np.asarray(depths), projector)


def sample_patterns(patterns: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """[N, H, W]: each pattern [N, Hp, Wp] sampled bilinearly at projector pixels uv [H, W, 2] (0 outside)."""
    import cv2

    return np.stack([cv2.remap(np.asarray(p, np.float32), uv[..., 0], uv[..., 1], cv2.INTER_LINEAR,
                               borderMode=cv2.BORDER_CONSTANT, borderValue=0.0) for p in patterns])


# cv2.remap wants image-like maps below 32767 pixels a side: a list of points is sampled as rows of this many
_REMAP_ROW = 4096


def sample_patterns_at(patterns: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """[N, P]: sample_patterns at a list of projector pixels uv [P, 2] (the same values per point)."""
    n = len(uv)
    padded = np.full((-(-n // _REMAP_ROW) * _REMAP_ROW, 2), OFF_IMAGE_PX, np.float32)
    padded[:n] = uv
    return sample_patterns(patterns, padded.reshape(-1, _REMAP_ROW, 2)).reshape(len(patterns), -1)[:, :n]


def predicted_intensities(depth: np.ndarray, camera, projector, patterns: np.ndarray) -> np.ndarray:
    """[N, H, W]: P_i(pi(x)) for each pixel's depth point x (0 outside the projector image or where depth is
    NaN). patterns [N, Hp, Wp], already blurred as rendered."""
    return sample_patterns(patterns, projector_coords(depth, camera, projector))


def least_squares_residual(images, codes, b_prior, ridge: float = LS_RIDGE):
    """[N, ...]: I - (a + b Q) with the offset a and modulation b solved per pixel in closed form, least
    squares over the frames (axis 0) of images [N, ...] and pattern values codes [N, ...]:
    b = (cov(Q, I) + ridge b_prior) / (var(Q) + ridge), clamped at >= 0 (a wrong depth must not explain the
    images by inverting the codes), a = mean(I) - b mean(Q). b_prior [...]: max - min of the images.
    Unlike min/max, this is exact for textured albedo and for codes that never reach 0 or 1 at a pixel.
    numpy arrays or torch tensors (broadcasting over the axes after the first), the same kind back."""
    a, b = least_squares_offset_modulation(images, codes, b_prior, ridge)
    return images - a - b * codes


def least_squares_offset_modulation(images, codes, b_prior, ridge: float = LS_RIDGE):
    """(a [...], b [...]): the per-pixel offset and modulation of `least_squares_residual`, fitted over the
    frames (axis 0) of images and codes [N, ...]; numpy arrays or torch tensors."""
    mq, mi = codes.mean(0), images.mean(0)
    cov = (codes * images).mean(0) - mq * mi
    var = (codes * codes).mean(0) - mq * mq
    b = (cov + ridge * b_prior) / (var + ridge)
    b = b.clamp_min(0.0) if isinstance(b, torch.Tensor) else np.maximum(b, 0.0)
    return mi - b * mq, b
