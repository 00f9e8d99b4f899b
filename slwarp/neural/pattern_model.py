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
    "least_squares_residual",
    "fit_blur_by_projector_depth",
    "refine_depth",
]

# minimum modulation b (full-scale units, images in [0, 1]) of a pixel lit with usable contrast
CONTRAST_THRESHOLD = 0.05
# projector pixel given to pixels without depth: off the image, so every pattern samples 0 there
OFF_IMAGE_PX = -10.0
# floor of the modulation b that the photometric residual is divided by (unlit pixels stay finite)
MIN_MODULATION = 1.0e-3
# least-squares offset/modulation: ridge pulling b toward max - min, in units of the codes' variance over the
# frames (it only matters where the codes barely vary, e.g. a point off the projector image)
LS_RIDGE = 0.02
# photometric refinement (`refine_depth`): blur ladder (projector px) the per-pixel blur interpolates in,
# projector-depth bins of the blur fit, window radius (px) and offset step (mm) of the search
BLUR_LADDER_STEP = 0.2
BLUR_LADDER = np.round(np.arange(0.0, 2.4 + 1e-9, BLUR_LADDER_STEP), 6)
BLUR_BINS = 6
REFINE_RADIUS = 3
REFINE_STEP_MM = 0.05


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


BLUR_FIT_PIXELS = 65536  # the blur is one number: this many evenly spread pixels pin it as well as all of them


def estimate_pattern_blur(camera, projector, images, patterns, depth, sigmas=None,
                          max_pixels: int = BLUR_FIT_PIXELS, device=None) -> tuple[float, dict]:
    """The Gaussian pattern blur (projector px) that best explains the images at a depth map [H, W] (mm).

    For each candidate sigma the patterns are blurred as the renderer blurs them (`blur_patterns`), sampled
    where each pixel's depth point projects, and compared with the images (a + b P); the sigma with the
    lowest mean squared residual over the pixels with depth and contrast (at most `max_pixels` of them, evenly
    spread over the list: the fit's cost no longer grows with the camera's resolution) wins, refined by a parabola
    through the best grid value and its neighbours. Depth errors of the search map (a fraction of a
    projector pixel) barely move the optimum. Returns (sigma, {sigma: mse}).
    """
    sigmas = np.round(np.arange(0.0, 2.51, 0.25), 2) if sigmas is None else np.asarray(sigmas, float)
    images = np.asarray(images, np.float32)
    a, b = offset_and_modulation(images)
    ok = np.isfinite(depth) & lit_with_contrast(b)
    if ok.sum() < 100:
        raise ValueError(f"estimate_pattern_blur: only {int(ok.sum())} pixels with depth and contrast")
    # the patterns are blurred where the training runs (device: a torch device; None: the CPU)
    pats = torch.as_tensor(np.asarray(patterns, np.float32), device=device)
    idx = np.flatnonzero(ok)
    if idx.size > max_pixels:
        idx = idx[np.linspace(0, idx.size - 1, max_pixels).astype(np.int64)]
    # the chosen pixels laid out as rows of 256 (OpenCV's remap wants image-like maps); the last row is padded
    # with repeats of the last pixel, which the mean leaves out
    n = idx.size
    rows = -(-n // 256)
    sel = np.concatenate([idx, np.full(rows * 256 - n, idx[-1])])
    rays = camera.pixel_to_ray(camera.pixel_grid().reshape(-1, 2)[sel])
    X = rays * (depth.reshape(-1)[sel].astype(np.float64) / rays[:, 2])[:, None]
    uv = np.asarray(projector.project_camera_points(X), np.float64)
    uv = np.where(np.isfinite(uv), uv, OFF_IMAGE_PX).astype(np.float32).reshape(rows, 256, 2)
    I = images.reshape(len(images), -1)[:, sel][:, :n]
    A, B = a.reshape(-1)[sel][:n], b.reshape(-1)[sel][:n]
    mse = {}
    for s in sigmas:
        pred = sample_patterns(blur_patterns(pats, float(s)).cpu().numpy(), uv).reshape(len(images), -1)[:, :n]
        mse[float(s)] = float(np.mean((I - A - B * pred) ** 2))
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


def least_squares_residual(images: np.ndarray, codes: np.ndarray, b_prior: np.ndarray, ridge: float = LS_RIDGE) -> np.ndarray:
    """[N, ...]: I - (a + b Q) with the offset a and modulation b solved per pixel in closed form, least
    squares over the frames (axis 0) of images [N, ...] and pattern values codes [N, ...]:
    b = (cov(Q, I) + ridge b_prior) / (var(Q) + ridge), clamped at >= 0 (a wrong depth must not explain the
    images by inverting the codes), a = mean(I) - b mean(Q). b_prior [...]: max - min of the images.
    Unlike min/max, this is exact for textured albedo and for codes that never reach 0 or 1 at a pixel."""
    mq, mi = codes.mean(0), images.mean(0)
    cov = (codes * images).mean(0) - mq * mi
    var = (codes * codes).mean(0) - mq * mq
    b = np.maximum((cov + ridge * b_prior) / (var + ridge), 0.0)
    return images - (mi - b * mq) - b * codes


def _projector_depth(depth: np.ndarray, camera, projector) -> np.ndarray:
    """[H, W] projector-frame z (mm) of each pixel's depth point; NaN where depth is NaN."""
    rays = camera.pixel_to_ray(camera.pixel_grid())
    with np.errstate(invalid="ignore"):
        X = rays * (np.asarray(depth, np.float64) / rays[..., 2])[..., None]
    return np.asarray(projector.camera_to_projector(X.reshape(-1, 3)), np.float64)[:, 2].reshape(depth.shape)


class _BlurLadder:
    """The patterns blurred at every sigma of BLUR_LADDER, sampled with a per-pixel sigma (linear between
    the two nearest rungs)."""

    def __init__(self, patterns: np.ndarray):
        pats = torch.as_tensor(np.asarray(patterns, np.float32))
        self.rungs = [blur_patterns(pats, float(s)).numpy() for s in BLUR_LADDER]

    def sample(self, uv: np.ndarray, sigma: np.ndarray) -> np.ndarray:
        """[N, H, W] at projector pixels uv [H, W, 2] with blur sigma [H, W] (px)."""
        pos = np.clip(sigma / BLUR_LADDER_STEP, 0, len(self.rungs) - 1 - 1e-6)
        lo = np.floor(pos).astype(np.int64)
        t = (pos - lo).astype(np.float32)
        out = 0.0
        for rung in np.unique(np.concatenate([np.unique(lo), np.unique(lo) + 1])):
            w = np.where(lo == rung, 1 - t, 0) + np.where(lo + 1 == rung, t, 0)
            if w.any():
                out = out + w * sample_patterns(self.rungs[rung], uv)
        return np.asarray(out, np.float32)


def fit_blur_by_projector_depth(depth: np.ndarray, camera, projector, images: np.ndarray, patterns: np.ndarray,
                                bins: int = BLUR_BINS) -> tuple[np.ndarray, np.ndarray]:
    """(z_p [K], sigma [K]): the pattern blur (projector px) that best explains the images at a depth map
    [H, W] (mm), one per projector-depth bin (equal pixel counts; fewer bins below 200 pixels each), at the
    bins' median projector z (mm). The projector's defocus grows with the distance from its focus plane, so
    one global sigma is too sharp at one end of the volume and too soft at the other. Each bin's sigma: the
    BLUR_LADDER rung of least mean squared least-squares residual, refined by a parabola.
    patterns [N, Hp, Wp] unblurred."""
    images = np.asarray(images, np.float32)
    _, b = offset_and_modulation(images)
    ok = np.isfinite(depth) & lit_with_contrast(b)
    if ok.sum() < 100:
        raise ValueError(f"fit_blur_by_projector_depth: only {int(ok.sum())} pixels with depth and contrast")
    bins = int(max(1, min(bins, ok.sum() // 200)))
    zp = _projector_depth(np.where(ok, depth, np.nan), camera, projector)[ok]
    edges = np.quantile(zp, np.linspace(0.0, 1.0, bins + 1))
    which = np.clip(np.searchsorted(edges, zp, side="right") - 1, 0, bins - 1)
    uv = projector_coords(np.where(ok, depth, np.nan), camera, projector)
    pats = torch.as_tensor(np.asarray(patterns, np.float32))
    mse = np.empty((len(BLUR_LADDER), bins))
    for j, s in enumerate(BLUR_LADDER):
        r = least_squares_residual(images[:, ok], sample_patterns(blur_patterns(pats, float(s)).numpy(), uv)[:, ok], b[ok])
        mse[j] = np.bincount(which, (r**2).mean(0), bins) / np.maximum(np.bincount(which, minlength=bins), 1)
    sigma = np.empty(bins)
    for k in range(bins):
        j = int(np.argmin(mse[:, k]))
        sigma[k] = BLUR_LADDER[j]
        if 0 < j < len(BLUR_LADDER) - 1:
            den = mse[j - 1, k] - 2 * mse[j, k] + mse[j + 1, k]
            if den > 0:
                sigma[k] += 0.5 * BLUR_LADDER_STEP * (mse[j - 1, k] - mse[j + 1, k]) / den
    centres = np.array([np.median(zp[which == k]) for k in range(bins)])
    return centres, sigma


def refine_depth(depth: np.ndarray, camera, projector, images: np.ndarray, patterns: np.ndarray, half_range_mm: float,
                 radius: int = REFINE_RADIUS, step_mm: float = REFINE_STEP_MM) -> np.ndarray:
    """Photometric refinement of a depth map [H, W] (mm, NaN: none): every pixel moves by the offset
    delta in +-half_range_mm (grid of step_mm, refined by a parabola) that, added to the depth of every pixel
    of its (2 radius + 1)^2 window, minimises the window's summed L1 model cost relative to b.

    The model here is the accurate one the study measured (bench/model_floor.py): offset and modulation per
    pixel by least squares (`least_squares_residual`) and the blur per projector depth
    (`fit_blur_by_projector_depth`, fitted at `depth` itself). Each pixel keeps its own depth plus the common
    offset (no planarity assumption), so it corrects the smooth part of the field's error the way a local
    decoder would; pixels without depth stay NaN. images [N, H, W], patterns [N, Hp, Wp] unblurred.
    """
    if not half_range_mm > 0 or not step_mm > 0:
        raise ValueError(f"refine_depth: half_range_mm and step_mm must be > 0, got {half_range_mm}, {step_mm}")
    depth = np.asarray(depth, np.float32)
    ok = np.isfinite(depth)
    if not ok.any():
        return depth.copy()
    import cv2

    images = np.asarray(images, np.float32)
    _, b = offset_and_modulation(images)
    centres, sigmas = fit_blur_by_projector_depth(depth, camera, projector, images, patterns)
    sigma = np.interp(np.nan_to_num(_projector_depth(depth, camera, projector), nan=float(centres[0])), centres, sigmas)
    ladder = _BlurLadder(patterns)
    deltas = np.arange(-half_range_mm, half_range_mm + 1e-9, step_mm)
    k = 2 * radius + 1
    # running argmin with the costs on either side of the best offset (for the parabola): O(H W) memory
    best = np.full(depth.shape, np.inf, np.float32)
    best_j = np.zeros(depth.shape, np.int64)
    left = np.full(depth.shape, np.nan, np.float32)
    right = np.full(depth.shape, np.nan, np.float32)
    prev = np.full(depth.shape, np.nan, np.float32)
    for j, delta in enumerate(deltas):
        shifted = np.where(ok, depth + np.float32(delta), np.nan)
        codes = ladder.sample(projector_coords(shifted, camera, projector), sigma)
        r = least_squares_residual(images, codes, b)
        cost = np.where(ok, np.abs(r).mean(0) / np.maximum(b, MIN_MODULATION), 0.0).astype(np.float32)
        cost = cv2.boxFilter(cost, -1, (k, k), normalize=False, borderType=cv2.BORDER_CONSTANT)
        right = np.where(best_j == j - 1, cost, right)
        better = cost < best
        best = np.where(better, cost, best)
        best_j = np.where(better, j, best_j)
        left = np.where(better, prev, left)
        right = np.where(better, np.nan, right)
        prev = cost
    den = left - 2 * best + right
    inner = np.isfinite(den) & (den > 0)
    frac = np.where(inner, 0.5 * (left - right) / np.where(inner, den, 1.0), 0.0)
    offset = deltas[best_j] + step_mm * frac
    return np.where(ok, depth + offset, np.nan).astype(np.float32)
