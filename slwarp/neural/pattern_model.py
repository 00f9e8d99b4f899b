"""The pattern model: what a camera pixel sees when the projector shows pattern P_i.

    I_i(r) = a(r) + b(r) P_i(pi(x))

x is the surface point seen by camera pixel r (camera frame, mm), pi(x) its projector pixel (OpenCV
distortion included), P_i the pattern as the camera sees it (Gaussian-blurred by `pattern_blur`
projector px: projector defocus and the camera pixel's footprint), a(r) = min_i I_i(r) the offset
(ambient light) and b(r) = max_i I_i(r) - a(r) the modulation. A pixel takes part (in training, the depth
search and the blur fit) when it is lit with contrast: b(r) > CONTRAST_THRESHOLD.

This module holds that model for the host side (numpy, OpenCV) and the pattern blur (torch):
offset and modulation, the contrast test, the blur, projector coordinates of a depth map, patterns
sampled there, the photometric residual and filter of a depth map, and the fit of the blur. The fused
renderer evaluates the same model per sample in Warp (slwarp.kernels.render) and its twin in torch
(slwarp.neural.twin).
"""
from __future__ import annotations

import numpy as np
import torch

__all__ = [
    "CONTRAST_THRESHOLD",
    "offset_and_modulation",
    "lit_with_contrast",
    "blur_patterns",
    "projector_coords",
    "sample_patterns",
    "predicted_intensities",
    "photometric_residual",
    "photometric_filter",
    "estimate_pattern_blur",
]

# minimum modulation b (full-scale units, images in [0, 1]) of a pixel lit with usable contrast
CONTRAST_THRESHOLD = 0.05
# projector pixel given to pixels without depth: off the image, so every pattern samples 0 there
OFF_IMAGE_PX = -10.0
# floor of the modulation b that the photometric residual is divided by (unlit pixels stay finite)
MIN_MODULATION = 1.0e-3


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
    p = patterns[:, None]
    p = torch.nn.functional.conv2d(torch.nn.functional.pad(p, (r, r, 0, 0), mode="replicate"), k.view(1, 1, 1, -1))
    p = torch.nn.functional.conv2d(torch.nn.functional.pad(p, (0, 0, r, r), mode="replicate"), k.view(1, 1, -1, 1))
    return p[:, 0].contiguous()


def projector_coords(depth: np.ndarray, camera, projector) -> np.ndarray:
    """[H, W, 2] float32 projector pixel where each pixel's depth point (camera z, mm) projects;
    OFF_IMAGE_PX where depth is NaN or the point does not project."""
    rays = camera.pixel_to_ray(camera.pixel_grid())
    with np.errstate(invalid="ignore"):
        X = rays * (np.asarray(depth, np.float64) / rays[..., 2])[..., None]
        uv = np.asarray(projector.project_camera_points(X.reshape(-1, 3)), np.float64).reshape(camera.height, camera.width, 2)
    return np.where(np.isfinite(uv), uv, OFF_IMAGE_PX).astype(np.float32)


def sample_patterns(patterns: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """[N, H, W]: each pattern [N, Hp, Wp] sampled bilinearly at projector pixels uv [H, W, 2] (0 outside)."""
    import cv2

    return np.stack([cv2.remap(np.asarray(p, np.float32), uv[..., 0], uv[..., 1], cv2.INTER_LINEAR,
                               borderMode=cv2.BORDER_CONSTANT, borderValue=0.0) for p in patterns])


def predicted_intensities(depth: np.ndarray, camera, projector, patterns: np.ndarray) -> np.ndarray:
    """[N, H, W]: P_i(pi(x)) for each pixel's depth point x (0 outside the projector image or where depth is
    NaN). patterns [N, Hp, Wp], already blurred as rendered."""
    return sample_patterns(patterns, projector_coords(depth, camera, projector))


def photometric_residual(depth: np.ndarray, camera, projector, images: np.ndarray, patterns: np.ndarray) -> np.ndarray:
    """[H, W]: RMS over the frames of I - (a + b P(pi(x))), relative to the pixel's modulation b (a, b as in
    `offset_and_modulation`); NaN where depth is NaN. patterns as rendered (blurred)."""
    images = np.asarray(images, np.float32)
    a, b = offset_and_modulation(images)
    pred = predicted_intensities(depth, camera, projector, patterns)
    r = np.sqrt(np.mean((images - a - b * pred) ** 2, axis=0)) / np.maximum(b, MIN_MODULATION)
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


def estimate_pattern_blur(camera, projector, images, patterns, depth, sigmas=None) -> tuple[float, dict]:
    """The Gaussian pattern blur (projector px) that best explains the images at a depth map [H, W] (mm).

    For each candidate sigma the patterns are blurred as the renderer blurs them (`blur_patterns`), sampled
    where each pixel's depth point projects, and compared with the images (a + b P); the sigma with the
    lowest mean squared residual over the pixels with depth and contrast wins, refined by a parabola
    through the best grid value and its neighbours. Depth errors of the search map (a fraction of a
    projector pixel) barely move the optimum. Returns (sigma, {sigma: mse}).
    """
    sigmas = np.round(np.arange(0.0, 2.51, 0.25), 2) if sigmas is None else np.asarray(sigmas, float)
    images = np.asarray(images, np.float32)
    a, b = offset_and_modulation(images)
    ok = np.isfinite(depth) & lit_with_contrast(b)
    if ok.sum() < 100:
        raise ValueError(f"estimate_pattern_blur: only {int(ok.sum())} pixels with depth and contrast")
    pats = torch.as_tensor(np.asarray(patterns, np.float32))
    uv = projector_coords(np.where(ok, depth, np.nan), camera, projector)  # the same for every sigma
    mse = {}
    for s in sigmas:
        pred = sample_patterns(blur_patterns(pats, float(s)).numpy(), uv)
        mse[float(s)] = float(np.mean(((images - a - b * pred) ** 2)[:, ok]))
    keys = sorted(mse)
    j = keys.index(min(mse, key=mse.get))
    best = keys[j]
    if 0 < j < len(keys) - 1:  # parabola through the best grid point and its neighbours (evenly spaced grid)
        y0, y1, y2 = mse[keys[j - 1]], mse[keys[j]], mse[keys[j + 1]]
        h = keys[j + 1] - keys[j]
        den = y0 - 2.0 * y1 + y2
        if den > 0 and abs((keys[j] - keys[j - 1]) - h) < 1e-9:
            best = float(keys[j] + 0.5 * h * (y0 - y2) / den)
    return round(best, 3), mse
