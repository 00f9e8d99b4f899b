"""The photometric refinement of a depth map (`refine_depth`) with the accurate model (offset and modulation by least
squares, the blur per projector depth), whether that model fits the images (`model_misfit`, `refine_where_model_fits`)
and whether a refinement explains frames it did not see (`refinement_generalises`); in torch on any device, numpy in
and out.
"""
from __future__ import annotations

import typing

import numpy as np
import torch

from .blur import (BLUR_BINS, _BlurLadder, _device, _fit_blur, _interp, _projector_uv, _Rays, _rays_in_projector,
                   fit_blur_by_projector_depth)
from .image import (MIN_MODULATION, blur_patterns, least_squares_offset_modulation, least_squares_residual,
                    lit_with_contrast, offset_and_modulation, projector_coords, sample_patterns)

__all__ = ["REFINE_RADIUS", "REFINE_STEP_MM", "model_misfit", "refine_where_model_fits", "refine_depth",
           "refinement_generalises"]

# photometric refinement (`refine_depth`): window radius (px) and offset step (mm) of the search
REFINE_RADIUS = 3
REFINE_STEP_MM = 0.05


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
    plate's RMS (bench/results/model-misfit-cpu.md; docs/accuracy.md, section 14)."""
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


def _fit_model(depth, camera, projector, images, patterns, device, ladder: _BlurLadder | None = None) -> _FittedModel | None:
    """The model fitted at depth (its blur per projector depth); None with fewer than 100 lit pixels with depth.
    ladder: the patterns' blur ladder when the caller has it (patterns then unused)."""
    dev = _device(device)
    d = torch.as_tensor(np.asarray(depth, np.float32), device=dev)
    has = torch.isfinite(d)
    img = torch.as_tensor(images, dtype=torch.float32, device=dev)
    _, b = offset_and_modulation(img)
    ok = has & lit_with_contrast(b)
    if int(ok.sum()) < 100:
        return None
    rays = _rays_in_projector(camera, projector, dev)
    ladder = _BlurLadder(patterns, dev) if ladder is None else ladder
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
    one worse. Real capture, 7 row-code images, the full decode refined (ad-hoc script, docs/accuracy.md section
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
