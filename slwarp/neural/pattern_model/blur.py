"""The pattern blur fitted to the images: one Gaussian sigma (projector px) at a depth map (`estimate_pattern_blur`,
the training's start), or one per projector-depth bin (`fit_blur_by_projector_depth`, the photometric refinement's
model), with the patterns blurred at every sigma of a ladder (`_BlurLadder`) and each pixel's ray in the projector
frame (`_Rays`), in torch on any device.
"""
from __future__ import annotations

import numpy as np
import torch

from ...scans.scanner import bounded_cache, camera_rays
from .image import (OFF_IMAGE_PX, blur_patterns, least_squares_residual, lit_with_contrast, offset_and_modulation,
                    projector_coords_at, sample_patterns_at)

__all__ = ["BLUR_FIT_PIXELS", "BLUR_LADDER_STEP", "BLUR_LADDER", "BLUR_BINS", "estimate_pattern_blur",
           "fit_blur_by_projector_depth"]

# the blur per projector depth (`fit_blur_by_projector_depth`, the photometric refinement's model): blur ladder
# (projector px) the per-pixel blur interpolates in, projector-depth bins of the fit
BLUR_LADDER_STEP = 0.2
BLUR_LADDER = np.round(np.arange(0.0, 2.4 + 1e-9, BLUR_LADDER_STEP), 6)
BLUR_BINS = 6

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
    """`fit_blur_by_projector_depth` on tensors: (z_p [K], sigma [K]) float64 on the device. Host
    synchronisations: the pixel count, the bins holding pixels, and the per-bin parabola on the K x R costs.
    A pixel whose ray is not finite or whose depth is not in front of the camera is left out (a NaN among the
    projector depths made every quantile NaN and left all but one bin empty); a bin without pixels (many pixels at
    one projector depth make equal edges) gives no (z_p, sigma): K can be below `bins`."""
    ok = ok & (depth > 0) & torch.isfinite(rays.ray).all(-1)
    n_ok = int(ok.sum())
    if n_ok < 100:
        raise ValueError(f"fit_blur_by_projector_depth: only {n_ok} pixels with depth and contrast")
    bins = int(max(1, min(bins, n_ok // 200)))
    X = rays.ray[ok] * depth[ok].double()[:, None] + rays.T  # [P, 3] projector frame
    zp = X[:, 2]
    edges = torch.quantile(zp, torch.linspace(0.0, 1.0, bins + 1, dtype=zp.dtype, device=zp.device))
    which = (torch.searchsorted(edges, zp.contiguous(), right=True) - 1).clamp(0, bins - 1)
    uv = _projector_uv(X.float(), projector)
    count = torch.bincount(which, minlength=bins)
    held = count.nonzero()[:, 0].tolist()  # the bins with pixels, in increasing z_p
    count = count.clamp_min(1).double()
    img, bb = images[:, ok], b[ok]
    mse = []
    for j in range(len(BLUR_LADDER)):
        codes = ladder.sample(uv, torch.full_like(bb, min(float(j), ladder.r - 1 - 1e-6)))  # rung j (the last: inside)
        r = least_squares_residual(img, codes, bb)
        mse.append(torch.bincount(which, (r * r).mean(0).double(), bins) / count)
    centres = torch.stack([torch.quantile(zp[which == k], 0.5) for k in held])
    mse = torch.stack(mse).cpu().numpy()[:, held]  # [R, K]
    sigma = np.empty(len(held))
    for k in range(len(held)):
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
