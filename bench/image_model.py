"""The structured-light image model as the accuracy study scripts evaluate it (numpy/torch on the CPU): the
patterns blurred at a ladder of sigmas, the model I_i = a + b Q_i with a, b from min/max or least squares, the
fits of the pattern blur (global or per projector-depth bin) and of the camera gamma, and the photometric depth
refinement (`refine_depth`) that the study found to pay most.

Used by bench/model_floor.py, bench/train_ablation.py and bench/extraction_study.py; a prototype of what the
library would do in Warp kernels (see the study's recipe), not part of the library.
"""
from __future__ import annotations

import numpy as np
import torch

SIGMA_STEP = 0.2  # projector px between the blurred pattern stacks (linear interpolation between them)
SIGMA_MAX = 2.4
GAMMAS = np.round(np.arange(1.0, 3.01, 0.1), 2)


class PatternStack:
    """The patterns blurred at sigma = 0, SIGMA_STEP, ..., SIGMA_MAX (as the renderer blurs them), sampled
    bilinearly at projector pixels with a per-sample sigma (linear between the two nearest stacks); taps
    outside the projector image count 0, as in the renderer."""

    def __init__(self, patterns: np.ndarray):
        from slwarp.neural.pattern_model import blur_patterns

        self.sigmas = np.round(np.arange(0.0, SIGMA_MAX + 1e-9, SIGMA_STEP), 6)
        pats = torch.as_tensor(np.asarray(patterns, np.float32))
        self.N, self.H, self.W = pats.shape
        stack = torch.stack([blur_patterns(pats, float(s)) for s in self.sigmas])  # [L, N, H, W]
        self.flat = stack.permute(0, 2, 3, 1).reshape(-1, self.N).contiguous()  # [(L H W), N]

    def _bilinear(self, level: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        u0, v0 = torch.floor(u), torch.floor(v)
        fu, fv = u - u0, v - v0
        iu, iv = u0.long(), v0.long()
        out = torch.zeros(u.shape[0], self.N)
        for dy in (0, 1):
            for dx in (0, 1):
                x, y = iu + dx, iv + dy
                ok = (x >= 0) & (x < self.W) & (y >= 0) & (y < self.H)
                w = (fu if dx else 1 - fu) * (fv if dy else 1 - fv) * ok
                idx = (level * self.H + y.clamp(0, self.H - 1)) * self.W + x.clamp(0, self.W - 1)
                out += w[:, None] * self.flat[idx]
        return out

    def sample(self, uv: np.ndarray, sigma: np.ndarray | float) -> np.ndarray:
        """[M, N] pattern values at projector pixels uv [M, 2] (NaN: off), blur sigma [M] or a number (px)."""
        uv = torch.as_tensor(np.nan_to_num(uv, nan=-1e6), dtype=torch.float32)
        lev = np.clip(np.broadcast_to(np.asarray(sigma, np.float64), (uv.shape[0],)) / SIGMA_STEP, 0, len(self.sigmas) - 1)
        l0 = np.minimum(np.floor(lev), len(self.sigmas) - 2).astype(np.int64) if len(self.sigmas) > 1 else np.zeros(len(lev), np.int64)
        t = torch.as_tensor(lev - l0, dtype=torch.float32)[:, None]
        l0t = torch.as_tensor(l0)
        q = (1 - t) * self._bilinear(l0t, uv[:, 0], uv[:, 1])
        if len(self.sigmas) > 1:
            q += t * self._bilinear(l0t + 1, uv[:, 0], uv[:, 1])
        return q.numpy()


def model_residual(images: np.ndarray, q: np.ndarray, ab: str, a0: np.ndarray, b0: np.ndarray,
                   ridge: float = 0.02) -> np.ndarray:
    """Residuals I - (a + b Q) [..., P, N] for images [P, N] and pattern values q [..., P, N].

    ab "minmax": a0, b0 [P] (min and max - min); "ls": per pixel (and hypothesis) least squares of a, b with
    a ridge pulling b toward b0 (weight `ridge` x N, in units of Q's variance: only matters where the codes
    barely vary over the frames), b clamped at >= 0 (a wrong depth cannot explain the images by inverting
    the codes)."""
    if ab == "minmax":
        return images - a0[:, None] - b0[:, None] * q
    mq, mi = q.mean(-1), images.mean(-1)
    cov = (q * images).mean(-1) - mq * mi
    var = (q * q).mean(-1) - mq * mq
    b = np.maximum((cov + ridge * b0) / (var + ridge), 0.0)
    a = mi - b * mq
    return images - a[..., None] - b[..., None] * q


def projector_uv_z(rays: np.ndarray, depth: np.ndarray, projector) -> tuple[np.ndarray, np.ndarray]:
    """Projector pixels [..., 2] and projector-frame z [...] (mm) of the points at camera z = depth on rays."""
    X = rays * (depth / rays[..., 2])[..., None]
    return projector.project_camera_points(X), projector.camera_to_projector(X)[..., 2]


def fit_sigma(stack: PatternStack, images, uv, ab, a0, b0, select=None) -> float:
    """The global blur (px) with the least mean squared residual of the model at uv (grid, then a parabola)."""
    sel = slice(None) if select is None else select
    mse = []
    for s in stack.sigmas:
        q = stack.sample(uv[sel], s)
        mse.append(float(np.mean(model_residual(images[sel], q, ab, a0[sel], b0[sel]) ** 2)))
    j = int(np.argmin(mse))
    best = float(stack.sigmas[j])
    if 0 < j < len(mse) - 1:
        den = mse[j - 1] - 2 * mse[j] + mse[j + 1]
        if den > 0:
            best += 0.5 * SIGMA_STEP * (mse[j - 1] - mse[j + 1]) / den
    return best


def fit_depth_sigma(stack, images, uv, zp, ab, a0, b0, bins: int = 6):
    """sigma(z_p): one global fit per projector-depth bin (equal counts), linear in z_p between bin centres."""
    edges = np.quantile(zp, np.linspace(0, 1, bins + 1))
    centres, sig = [], []
    for k in range(bins):
        sel = (zp >= edges[k]) & (zp <= edges[k + 1])
        if sel.sum() < 50:
            continue
        centres.append(float(np.median(zp[sel])))
        sig.append(fit_sigma(stack, images, uv, ab, a0, b0, sel))
    return np.asarray(centres), np.asarray(sig)


def fit_gamma(images, q, ab) -> float:
    """The gamma whose linearised images I ** gamma the model explains best (least relative residual);
    q [P, N]: the model's pattern values at the pixels."""
    best, best_cost = 1.0, np.inf
    for g in GAMMAS:
        lin = images ** g
        a0 = lin.min(-1)
        b0 = lin.max(-1) - a0
        r = model_residual(lin, q, ab, a0, b0)
        cost = float(np.mean(np.sqrt(np.mean(r**2, -1)) / np.maximum(b0, 1e-3)))
        if cost < best_cost:
            best, best_cost = float(g), cost
    return best


def fit_model(scan, depth: np.ndarray, ab: str = "ls", blur: str = "depth", bins: int = 6):
    """(sigma_fn, info): the pattern blur explaining the images at a depth map [H, W] (NaN: unused), as a
    function of projector z (mm) -> sigma (px): blur "global" (one sigma) or "depth" (one per projector-depth
    bin, linear between bin centres); ab: the a, b model used for the fit."""
    cam, prj = scan.camera, scan.projector
    ok = np.isfinite(depth)
    rays = cam.pixel_to_ray(cam.pixel_grid())[ok]
    uv, zp = projector_uv_z(rays, depth[ok].astype(np.float64), prj)
    obs = scan.images[:, ok].T.astype(np.float64)
    stack = PatternStack(scan.patterns)
    a0 = obs.min(1)
    b0 = obs.max(1) - a0
    if blur == "global":
        s = fit_sigma(stack, obs, uv, ab, a0, b0)
        return (lambda z, s=s: np.full_like(np.asarray(z, np.float64), s)), {"sigma": s}
    zc, sc = fit_depth_sigma(stack, obs, uv, zp, ab, a0, b0, bins)
    return (lambda z: np.interp(z, zc, sc)), {"z_p": zc.tolist(), "sigma": sc.tolist()}


def refine_depth(scan, depth: np.ndarray, sigma_fn, ab: str = "ls", radius: int = 3, half_range: float = 3.0,
                 step: float = 0.05) -> np.ndarray:
    """Photometric refinement of a depth map [H, W] (mm, NaN invalid): for every pixel, the offset delta in
    +-half_range (grid of `step`, refined by a parabola) that, added to the depth of every pixel of its
    (2 radius + 1)^2 window, minimises the window's summed L1 model cost (relative to b); the pixel's depth
    moves by that offset. Each pixel keeps its own depth plus the common offset (no planarity assumption),
    so the step corrects the smooth part of a depth map's error the way a local decoder would.
    sigma_fn: projector z (mm) -> blur sigma (px), see `fit_model`; ab: "ls" or "minmax".
    """
    import cv2

    cam, prj = scan.camera, scan.projector
    H, W = depth.shape
    ok = np.isfinite(depth)
    obs = scan.images.reshape(len(scan.images), -1).T[ok.ravel()].astype(np.float64)
    a0 = obs.min(1)
    b0 = obs.max(1) - a0
    rays = cam.pixel_to_ray(cam.pixel_grid()).reshape(-1, 3)[ok.ravel()]
    d0 = depth[ok].astype(np.float64)
    stack = PatternStack(scan.patterns)
    sig = sigma_fn(projector_uv_z(rays, d0, prj)[1])
    deltas = np.arange(-half_range, half_range + 1e-9, step)
    cost = np.zeros((len(deltas), H, W), np.float32)
    flat = np.zeros(H * W, np.float32)
    k = 2 * radius + 1
    for h, dl in enumerate(deltas):
        uv, _ = projector_uv_z(rays, d0 + dl, prj)
        r = model_residual(obs, stack.sample(uv, sig), ab, a0, b0)
        flat[ok.ravel()] = np.abs(r).mean(1) / np.maximum(b0, 1e-3)
        cost[h] = cv2.boxFilter(flat.reshape(H, W), -1, (k, k), normalize=False, borderType=cv2.BORDER_CONSTANT)
    j = cost.argmin(0)
    jj = np.clip(j, 1, len(deltas) - 2)
    iy, ix = np.indices((H, W))
    c0, c1, c2 = cost[jj - 1, iy, ix], cost[jj, iy, ix], cost[jj + 1, iy, ix]
    den = c0 - 2 * c1 + c2
    inner = (j > 0) & (j < len(deltas) - 1) & (den > 0)
    offset = deltas[j] + np.where(inner, 0.5 * step * (c0 - c2) / np.where(den > 0, den, 1.0), 0.0)
    return np.where(ok, depth + offset, np.nan).astype(np.float32)
