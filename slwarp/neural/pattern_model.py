"""The pattern model: what a camera pixel sees when the projector shows pattern P_i.

    I_i(r) = a(r) + b(r) P_i(pi(x))

x is the surface point seen by camera pixel r (camera frame, mm), pi(x) its projector pixel (OpenCV
distortion included), P_i the pattern as the camera sees it (Gaussian-blurred by `pattern_blur`
projector px: projector defocus and the camera pixel's footprint), a(r) = min_i I_i(r) the offset
(ambient light) and b(r) = max_i I_i(r) - a(r) the modulation. A pixel takes part (in training, the depth
search and the blur fit) when it is lit with contrast: b(r) > CONTRAST_THRESHOLD.

This module holds that model for the host side (numpy, OpenCV) and the pattern blur (torch):
offset and modulation, the contrast test, the blur, projector coordinates of a depth map, patterns
sampled there, the photometric residual and filter of a depth map, and the fit of the blur; the
photometric refinement of a depth map (`refine_depth`) and its blur fit per projector depth run in torch on
any device (numpy in and out). The fused
renderer evaluates the same model per sample in Warp (slwarp.kernels.render) and its twin in torch
(slwarp.neural.ops.twin).
"""
from __future__ import annotations

import typing

import numpy as np
import torch

from ..scans.scanner import bounded_cache, camera_rays
from .config import CONTRAST_THRESHOLD  # the config holds the default; re-exported for the renderer
from .ops.twin import bilinear_patterns

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
    return _project_rays(camera_rays(camera).reshape(-1, 3)[index], np.asarray(depth).reshape(-1)[index], projector)


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


# below this share of pixels with depth, photometric_residual works on those pixels only (the same values): the
# extraction asks it about a few candidates at a time (the repair's changes, its growth, the edge readmission)
SPARSE_SHARE = 0.25


def _relative_rms(images, a, b, pred):
    """RMS over the frames (axis 0) of images - a - b pred, over max(b, MIN_MODULATION)."""
    return np.sqrt(np.mean((images - a - b * pred) ** 2, axis=0)) / np.maximum(b, MIN_MODULATION)


def _sparse_residual(depth: np.ndarray, camera, projector, images: np.ndarray, patterns: np.ndarray) -> np.ndarray:
    """photometric_residual computed at the finite pixels of depth only (the same arithmetic per pixel)."""
    out = np.full(depth.shape, np.nan, np.float32)
    index = np.flatnonzero(np.isfinite(depth))
    if index.size:
        obs = images.reshape(len(images), -1)[:, index]  # [N, P]
        a, b = offset_and_modulation(obs)
        pred = sample_patterns_at(patterns, projector_coords_at(index, depth, camera, projector))
        out.reshape(-1)[index] = _relative_rms(obs, a, b, pred)
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
        rays = _rays_on(camera, dev)[idx]
        uv = projector.project_camera_points(rays * (flat[idx].double() / rays[:, 2])[:, None])
        uv = torch.where(torch.isfinite(uv), uv, torch.full_like(uv, OFF_IMAGE_PX)).float()
        pred = bilinear_patterns(patterns.float(), uv).t()  # [N, P]
        obs = torch.as_tensor(images, dtype=torch.float32, device=dev).reshape(len(pred), -1)[:, idx]  # [N, P]
        a, b = offset_and_modulation(obs)
        diff = obs - a - b * pred
        total = diff[0] * diff[0]
        for k in range(1, len(diff)):  # frame by frame, as numpy sums an axis-0 mean
            total = total + diff[k] * diff[k]
        out[idx] = torch.sqrt(total / len(diff)) / torch.clamp(b, min=MIN_MODULATION)
    return out.reshape(np.shape(depth)).cpu().numpy()


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
    uv = projector_coords_at(idx, depth, camera, projector)
    I = images.reshape(len(images), -1)[:, idx]
    A, B = a.reshape(-1)[idx], b.reshape(-1)[idx]
    mse = {}
    for s in sigmas:
        pred = sample_patterns_at(blur_patterns(pats, float(s)).cpu().numpy(), uv)
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


class _Rays:
    """Each camera pixel's ray scaled to camera z = 1, in the projector frame: the pixel's point at depth d
    (camera z, mm) is d ray + T in the projector frame (X_p = R X_c + T), one multiply-add per depth instead
    of a rotation. `ray` [H, W, 3] float64 on the device (computed on the host through the scanner's geometry),
    `ray32` its float32 copy, `T` [3]."""

    def __init__(self, camera, projector, device):
        rays = camera_rays(camera)
        self.ray = torch.as_tensor(np.asarray(rays / rays[..., 2:3], np.float64) @ projector.R.T, device=device)
        self.ray32 = self.ray.float()
        self.T = torch.as_tensor(projector.T, dtype=torch.float64, device=device)
        self.T32 = self.T.float()


# the last few rigs' _Rays per device (the refinement's model is fitted once per extraction; building them on the
# host and uploading them took 0.04 s of `fast`'s 0.2 s refinement on an H100)
_PROJECTOR_RAYS: dict = {}


def _rays_in_projector(camera, projector, device) -> _Rays:
    """_Rays(camera, projector, device), built once per rig and device."""
    key = camera.cache_key + (np.asarray(projector.R).tobytes(), np.asarray(projector.T).tobytes(), str(device))
    return bounded_cache(_PROJECTOR_RAYS, key, lambda: _Rays(camera, projector, device))


def _projector_uv(points: torch.Tensor, projector) -> torch.Tensor:
    """[..., 2] projector pixels of projector-frame points [..., 3] (the scanner's torch path: OpenCV
    distortion, NaN behind the lens or outside the trusted field), OFF_IMAGE_PX where NaN (as
    `projector_coords`)."""
    uv = projector.project(points)
    return torch.where(torch.isfinite(uv), uv, torch.full_like(uv, OFF_IMAGE_PX))


class _BlurLadder:
    """The patterns blurred at every sigma of BLUR_LADDER as one volume [1, N, R, Hp, Wp] on a device, sampled
    at projector pixels with a per-pixel sigma: one trilinear grid_sample, bilinear in the pixel (pixel centres
    at integer coordinates, zeros outside the image: cv2.remap INTER_LINEAR with BORDER_CONSTANT 0, without
    its 1/32 px fixed-point rounding of the coordinates) and linear between the two nearest rungs."""

    def __init__(self, patterns, device):
        pats = torch.as_tensor(patterns, dtype=torch.float32, device=device)
        tf32 = torch.backends.cudnn.allow_tf32  # the trainer switches TF32 on: 10-bit mantissas in the blur's convolutions
        torch.backends.cudnn.allow_tf32 = False
        try:
            self.rungs = torch.stack([blur_patterns(pats, float(s)) for s in BLUR_LADDER], dim=1)[None]
        finally:
            torch.backends.cudnn.allow_tf32 = tf32
        _, self.n, self.r, self.hp, self.wp = self.rungs.shape

    def sample(self, uv: torch.Tensor, pos: torch.Tensor) -> torch.Tensor:
        """[N, *S]: the patterns at projector pixels uv [*S, 2] and ladder positions pos [*S] (sigma /
        BLUR_LADDER_STEP, in [0, R - 1]). S: up to 3 dimensions."""
        shape = pos.shape
        uv3 = uv.reshape((1,) * (3 - len(shape)) + tuple(shape) + (2,))
        p3 = pos.reshape(uv3.shape[:-1])
        # align_corners=False: normalised -1 and 1 are the outer edges of the first and last pixel
        grid = torch.stack([(2.0 * uv3[..., 0] + 1.0) / self.wp - 1.0, (2.0 * uv3[..., 1] + 1.0) / self.hp - 1.0,
                            (2.0 * p3 + 1.0) / self.r - 1.0], dim=-1)
        out = torch.nn.functional.grid_sample(self.rungs, grid[None], mode="bilinear", padding_mode="zeros",
                                              align_corners=False)
        return out[0].reshape((self.n,) + tuple(shape))

    def position(self, sigma: torch.Tensor) -> torch.Tensor:
        """Ladder position of a blur sigma (px), clamped to the ladder as the rungs' interpolation needs."""
        return (sigma / BLUR_LADDER_STEP).clamp(0.0, self.r - 1 - 1e-6)


def _interp(x: torch.Tensor, xp: torch.Tensor, fp: torch.Tensor) -> torch.Tensor:
    """np.interp in torch: piecewise linear through (xp, fp) (xp increasing), constant beyond the ends."""
    if xp.numel() == 1:
        return fp[0].expand_as(x).clone()
    i = torch.searchsorted(xp, x.contiguous(), right=True).clamp(1, xp.numel() - 1)
    x0, x1, f0, f1 = xp[i - 1], xp[i], fp[i - 1], fp[i]
    dx = x1 - x0
    t = torch.where(dx > 0, (x - x0) / torch.where(dx > 0, dx, torch.ones_like(dx)), torch.zeros_like(x))
    out = f0 + t.clamp(0.0, 1.0) * (f1 - f0)
    return torch.where(x <= xp[0], fp[0], torch.where(x >= xp[-1], fp[-1], out))


def _fit_blur(depth: torch.Tensor, ok: torch.Tensor, rays: _Rays, projector, images: torch.Tensor,
              b: torch.Tensor, ladder: _BlurLadder, bins: int) -> tuple[torch.Tensor, torch.Tensor]:
    """`fit_blur_by_projector_depth` on tensors: (z_p [K], sigma [K]) float64 on the device. One host
    synchronisation (the pixel count), and the per-bin parabola on the K x R costs on the host."""
    n_ok = int(ok.sum())
    if n_ok < 100:
        raise ValueError(f"fit_blur_by_projector_depth: only {n_ok} pixels with depth and contrast")
    bins = int(max(1, min(bins, n_ok // 200)))
    X = rays.ray[ok] * depth[ok].double()[:, None] + rays.T  # [P, 3] projector frame
    zp = X[:, 2]
    edges = torch.quantile(zp, torch.linspace(0.0, 1.0, bins + 1, dtype=zp.dtype, device=zp.device))
    which = (torch.searchsorted(edges, zp.contiguous(), right=True) - 1).clamp(0, bins - 1)
    uv = _projector_uv(X.float(), projector)
    count = torch.bincount(which, minlength=bins).clamp_min(1).double()
    img, bb = images[:, ok], b[ok]
    mse = []
    for j in range(len(BLUR_LADDER)):
        codes = ladder.sample(uv, torch.full_like(bb, min(float(j), ladder.r - 1 - 1e-6)))  # rung j (the last: inside)
        r = least_squares_residual(img, codes, bb)
        mse.append(torch.bincount(which, (r * r).mean(0).double(), bins) / count)
    centres = torch.stack([torch.quantile(zp[which == k], 0.5) for k in range(bins)])
    mse = torch.stack(mse).cpu().numpy()  # [R, K]
    sigma = np.empty(bins)
    for k in range(bins):
        j = int(np.argmin(mse[:, k]))
        sigma[k] = BLUR_LADDER[j]
        if 0 < j < len(BLUR_LADDER) - 1:
            den = mse[j - 1, k] - 2 * mse[j, k] + mse[j + 1, k]
            if den > 0:
                sigma[k] += 0.5 * BLUR_LADDER_STEP * (mse[j - 1, k] - mse[j + 1, k]) / den
    return centres, torch.as_tensor(sigma, device=centres.device)


def _device(device) -> torch.device:
    return torch.device(device) if device is not None else torch.device("cpu")


def fit_blur_by_projector_depth(depth: np.ndarray, camera, projector, images: np.ndarray, patterns: np.ndarray,
                                bins: int = BLUR_BINS, device=None) -> tuple[np.ndarray, np.ndarray]:
    """(z_p [K], sigma [K]): the pattern blur (projector px) that best explains the images at a depth map
    [H, W] (mm), one per projector-depth bin (equal pixel counts; fewer bins below 200 pixels each), at the
    bins' median projector z (mm). The projector's defocus grows with the distance from its focus plane, so
    one global sigma is too sharp at one end of the volume and too soft at the other. Each bin's sigma: the
    BLUR_LADDER rung of least mean squared least-squares residual, refined by a parabola.
    patterns [N, Hp, Wp] unblurred. Computed in torch on `device` (default CPU)."""
    dev = _device(device)
    d = torch.as_tensor(np.asarray(depth, np.float32), device=dev)
    img = torch.as_tensor(images, dtype=torch.float32, device=dev)
    _, b = offset_and_modulation(img)
    ok = torch.isfinite(d) & lit_with_contrast(b)
    centres, sigma = _fit_blur(d, ok, _rays_in_projector(camera, projector, dev), projector, img, b,
                               _BlurLadder(patterns, dev), bins)
    return centres.cpu().numpy(), sigma.cpu().numpy()


def model_misfit(depth: np.ndarray, camera, projector, images: np.ndarray, patterns: np.ndarray, device=None) -> float:
    """How well the refinement's pattern model explains the images at depth [H, W] (mm, NaN: none): the median over
    the lit pixels with depth of mean_n |I_n - (a + b Q_n)| / b, the per-pixel cost `refine_depth` minimises (a, b
    by least squares, Q the patterns [N, Hp, Wp] (unblurred) blurred per projector depth as fitted at `depth`).
    NaN when fewer than 100 pixels qualify.

    Why: where the model lacks part of the optics (a camera response, the real lens and projector), the
    refinement fits those errors instead of the surface. At the true depth of the simulator's linear-camera scans
    (8 scenes x 4 full-resolution rigs, 6 random patterns) it is 0.015 to 0.023 (the checker albedo highest; the same
    with pixel integration and a lens blur), where the refinement helps; 0.040 to 0.043 through a gamma-2.2 or sRGB
    camera, and 0.026 on the real capture (7 row-code images, at the full 40-image decode), where it doubles the
    plate's RMS (bench/results/model-misfit-cpu.md; notes/accuracy.md, section 14)."""
    model = _fit_model(depth, camera, projector, images, patterns, device)
    return float("nan") if model is None else _misfit(model)


class _FittedModel(typing.NamedTuple):
    """The refinement's pattern model fitted at a depth map (what `model_misfit` and `refine_depth` share): the depth
    d [H, W] and where it is finite (has), images [N, H, W], modulation b [H, W], rays, blur ladder and the blur per
    projector depth (centres, sigmas [K]), all torch on one device."""

    d: torch.Tensor
    has: torch.Tensor
    img: torch.Tensor
    b: torch.Tensor
    rays: "_Rays"
    ladder: "_BlurLadder"
    centres: torch.Tensor
    sigmas: torch.Tensor
    projector: object


def _fit_model(depth, camera, projector, images, patterns, device) -> _FittedModel | None:
    """The model fitted at depth (its blur per projector depth); None with fewer than 100 lit pixels with depth."""
    dev = _device(device)
    d = torch.as_tensor(np.asarray(depth, np.float32), device=dev)
    has = torch.isfinite(d)
    img = torch.as_tensor(images, dtype=torch.float32, device=dev)
    _, b = offset_and_modulation(img)
    ok = has & lit_with_contrast(b)
    if int(ok.sum()) < 100:
        return None
    rays = _rays_in_projector(camera, projector, dev)
    ladder = _BlurLadder(patterns, dev)
    centres, sigmas = _fit_blur(d, ok, rays, projector, img, b, ladder, BLUR_BINS)
    return _FittedModel(d, has, img, b, rays, ladder, centres, sigmas, projector)


def _misfit(m: _FittedModel) -> float:
    """model_misfit of a fitted model."""
    ok = m.has & lit_with_contrast(m.b)
    X = m.rays.ray[ok] * m.d[ok].double()[:, None] + m.rays.T  # [P, 3] projector frame
    pos = m.ladder.position(_interp(X[:, 2], m.centres, m.sigmas).float())
    codes = m.ladder.sample(_projector_uv(X.float(), m.projector), pos)
    r = least_squares_residual(m.img[:, ok], codes, m.b[ok])
    return float((r.abs().mean(0) / m.b[ok].clamp_min(MIN_MODULATION)).median())


def refine_where_model_fits(depth: np.ndarray, camera, projector, images: np.ndarray, patterns: np.ndarray,
                            half_range_mm: float, max_misfit: float,
                            device=None) -> tuple[np.ndarray | None, float | None]:
    """(refined, misfit): `refine_depth` of depth [H, W], or None when max_misfit > 0 and the `model_misfit` at depth
    is above it (the one place the limit is compared); misfit None when max_misfit <= 0. The model is fitted once
    for both."""
    depth = np.asarray(depth, np.float32)
    if not np.isfinite(depth).any():
        return depth.copy(), (float("nan") if max_misfit > 0 else None)
    model = _fit_model(depth, camera, projector, images, patterns, device)
    misfit = (float("nan") if model is None else _misfit(model)) if max_misfit > 0 else None
    if misfit is not None and misfit > max_misfit:
        return None, misfit
    return _refine(model, depth, half_range_mm, REFINE_RADIUS, REFINE_STEP_MM, 8), misfit


def refine_depth(depth: np.ndarray, camera, projector, images: np.ndarray, patterns: np.ndarray, half_range_mm: float,
                 radius: int = REFINE_RADIUS, step_mm: float = REFINE_STEP_MM, device=None,
                 chunk: int = 8) -> np.ndarray:
    """Photometric refinement of a depth map [H, W] (mm, NaN: none): every pixel moves by the offset
    delta in +-half_range_mm (grid of step_mm, refined by a parabola) that, added to the depth of every pixel
    of its (2 radius + 1)^2 window, minimises the window's summed L1 model cost relative to b.

    The model here is the accurate one the study measured (bench/model_floor.py): offset and modulation per
    pixel by least squares (`least_squares_residual`) and the blur per projector depth
    (`fit_blur_by_projector_depth`, fitted at `depth` itself). Each pixel keeps its own depth plus the common
    offset (no planarity assumption), so it corrects the smooth part of the field's error the way a local
    decoder would; pixels without depth stay NaN. images [N, H, W], patterns [N, Hp, Wp] unblurred.

    Runs in torch on `device` (default CPU; the trainer's device at extraction), numpy in and out: the offsets
    `chunk` at a time with a running argmin and no host synchronisation inside the loop over the offsets.
    Memory: about 110 bytes per pixel and offset of a chunk with N = 6 frames (measured on the CPU: 145 MB
    more for 16 more offsets on the small rig's 82k pixels), so ~1.2 GB for the default rig (1.3 M pixels)
    with chunk 8, plus the blur ladder (13 N Hp Wp floats: 0.33 GB for 6 frames of 1280 x 800)."""
    depth = np.asarray(depth, np.float32)
    if not np.isfinite(depth).any():
        return depth.copy()
    return _refine(_fit_model(depth, camera, projector, images, patterns, device), depth, half_range_mm, radius,
                   step_mm, chunk)


def _refine(m: _FittedModel | None, depth: np.ndarray, half_range_mm: float, radius: int, step_mm: float,
            chunk: int) -> np.ndarray:
    """refine_depth's search with the model fitted at depth (None: too few pixels to fit its blur)."""
    if not half_range_mm > 0 or not step_mm > 0:
        raise ValueError(f"refine_depth: half_range_mm and step_mm must be > 0, got {half_range_mm}, {step_mm}")
    if m is None:
        raise ValueError("fit_blur_by_projector_depth: fewer than 100 pixels with depth and contrast")
    d, ok, img, b, rays, ladder, centres, sigmas = m.d, m.has, m.img, m.b, m.rays, m.ladder, m.centres, m.sigmas
    dev, projector = d.device, m.projector
    # per-pixel blur from the pixel's projector depth (pixels without depth: the first bin's, as they cost 0)
    zp = rays.ray[..., 2] * d.double() + rays.T[2]
    pos = ladder.position(_interp(torch.nan_to_num(zp, nan=0.0).where(ok, centres[0]), centres, sigmas).float())
    deltas = np.arange(-half_range_mm, half_range_mm + 1e-9, step_mm)
    k = 2 * radius + 1
    inv_b = torch.where(ok, 1.0 / b.clamp_min(MIN_MODULATION), torch.zeros_like(b))  # 0: no cost without depth
    d0 = torch.where(ok, d, torch.zeros_like(d))
    img4, b4 = img[:, None], b[None]  # [N, 1, H, W], [1, H, W]
    shape = depth.shape
    # running argmin with the costs on either side of the best offset (for the parabola): O(H W) memory
    best = torch.full(shape, float("inf"), device=dev)
    best_j = torch.zeros(shape, dtype=torch.int64, device=dev)
    left = torch.full(shape, float("nan"), device=dev)
    right = torch.full(shape, float("nan"), device=dev)
    prev = torch.full(shape, float("nan"), device=dev)
    nan1 = torch.full((1,) + shape, float("nan"), device=dev)
    all_deltas = torch.as_tensor(deltas.astype(np.float32), device=dev)
    chunk = max(1, int(chunk))
    for j0 in range(0, len(deltas), chunk):
        dl = all_deltas[j0 : j0 + chunk]
        c = dl.numel()
        shifted = d0[None] + dl[:, None, None]  # [C, H, W] float32, as depth + float32(delta)
        uv = _projector_uv(rays.ray32 * shifted[..., None] + rays.T32, projector)  # [C, H, W, 2]
        codes = ladder.sample(uv, pos.expand(c, *shape))  # [N, C, H, W]
        r = least_squares_residual(img4, codes, b4)
        cost = r.abs().mean(0) * inv_b  # [C, H, W]
        cost = torch.nn.functional.avg_pool2d(cost[:, None], k, stride=1, padding=radius,
                                              count_include_pad=True)[:, 0] * float(k * k)  # zero-padded box sum
        ext = torch.cat([prev[None], cost, nan1])  # [C + 2]: the offsets j0 - 1 .. j0 + C
        cmin, cidx = cost.min(dim=0)  # the first of equal minima, as the sequential scan keeps
        right = torch.where(best_j == j0 - 1, cost[0], right)
        better = cmin < best
        best = torch.where(better, cmin, best)
        best_j = torch.where(better, cidx + j0, best_j)
        left = torch.where(better, ext.gather(0, cidx[None])[0], left)
        right = torch.where(better, ext.gather(0, (cidx + 2)[None])[0], right)
        prev = cost[-1]
    den = left - 2 * best + right
    inner = torch.isfinite(den) & (den > 0)
    frac = torch.where(inner, 0.5 * (left - right) / torch.where(inner, den, torch.ones_like(den)), torch.zeros_like(den))
    offset = torch.as_tensor(deltas, device=dev)[best_j] + step_mm * frac.double()
    out = torch.where(ok, d.double() + offset, torch.full_like(offset, float("nan"))).float()
    return out.cpu().numpy()


def refinement_generalises(depth: np.ndarray, camera, projector, images, patterns: np.ndarray,
                           half_range_mm: float, device=None, refine=None) -> dict:
    """Whether the photometric refinement of depth [H, W] (mm, NaN: none) explains frames it did not see.

    For each frame k: the depth refined without frame k (`refine_depth`, or `refine` with its signature), and
    frame k's median relative residual |I_k - (a + b Q_k)| / b over the lit pixels with depth, at the depth before
    and after that refinement (a, b by least squares over the other frames; Q_k blurred by the median of the
    blur fitted at `depth`). Returns {"keep": mean change over the frames < 0, "before": [N], "after": [N]}.
    Fewer than 3 frames: nothing to hold out, keep.

    Why: a refinement that fits the model's errors, not the surface, fits the frames it sees and explains a new
    one worse. Real capture, 7 row-code images, the full decode refined (ad-hoc script, notes/accuracy.md section
    13): plate RMS 0.688 -> 1.495 mm, and the held-out median residual rose in all 7 folds (mean 0.0368 ->
    0.0392); simulator, small vertical rig, rods, a CPU field's map: MAE 1.056 -> 0.743 mm, and it fell in all 6
    (0.0270 -> 0.0265). But on full-resolution simulated scans (GPU, `tuned`, default rig) it also refused
    refinements that helped, on 4 of 8 scenes (mean MAE 0.134 -> 0.171 mm), so it is opt-in (`refine_check`), for
    real captures. Cost: N more refinements."""
    images = images.cpu().numpy() if isinstance(images, torch.Tensor) else np.asarray(images, np.float32)
    patterns = np.asarray(patterns, np.float32)
    depth = np.asarray(depth, np.float32)
    n = len(images)
    if n < 3 or not np.isfinite(depth).any():
        return {"keep": True, "before": [], "after": []}
    refine = refine_depth if refine is None else refine
    _, b_all = offset_and_modulation(images)
    lit = lit_with_contrast(b_all)
    _, sigma = fit_blur_by_projector_depth(depth, camera, projector, images, patterns, device=device)
    blurred = blur_patterns(torch.as_tensor(patterns), float(np.median(sigma))).numpy()
    before, after = [], []
    for k in range(n):
        seen = [i for i in range(n) if i != k]
        refined = refine(depth, camera, projector, images[seen], patterns[seen], half_range_mm, device=device)
        ok = lit & np.isfinite(depth) & np.isfinite(refined)
        if not ok.any():
            return {"keep": True, "before": [], "after": []}
        for d, out in ((depth, before), (refined, after)):
            codes = sample_patterns(blurred, projector_coords(np.where(ok, d, np.nan), camera, projector))
            a, b = least_squares_offset_modulation(images[seen][:, ok], codes[seen][:, ok], b_all[ok])
            r = np.abs(images[k][ok] - a - b * codes[k][ok]) / np.maximum(b_all[ok], MIN_MODULATION)
            out.append(float(np.median(r)))
    keep = float(np.mean(np.subtract(after, before))) < 0.0
    return {"keep": keep, "before": before, "after": after}
