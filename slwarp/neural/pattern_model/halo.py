"""The lens halo fitted to a scan: how much of the projected light the pattern model spreads into a wide halo
around the patterns (`with_halo`), chosen as the share under which the model explains the images best.

Why: on the real captures a Gray code edge is a Gaussian of about 0.7 projector px plus about 10% of the light
spread over about 40 px (bench/results/edge-profile-cpu.md). The model's misfit at the full decode falls from 0.026
to 0.017 (capture 0), 0.032 to 0.023 (capture 1) and 0.020 to 0.016 (capture 2) with a 0.1 halo, while the
simulator's linear and optics cameras fit best without one (bunny, steps, checker: misfit rises with any share).
A fixed share would put a halo into scans of lenses that have none; fitted, those keep 0.
"""
from __future__ import annotations

import copy

import numpy as np
import torch

from .blur import _BlurLadder, _device
from .image import blur_patterns, with_halo
from .refine import _fit_model, _misfit

# the shares tried (of the projected light), the halo's width (projector px; the real capture's, bench.edge_profile)
HALO_SHARES = (0.0, 0.05, 0.1, 0.15, 0.2, 0.25)
HALO_SIGMA = 40.0
# a halo is kept only when it lowers the misfit by this fraction of the misfit without one (the noise of the fit:
# the simulator's random patterns through a halo camera gain under 1%, real Gray code captures 19-36%)
HALO_MIN_GAIN = 0.05
# pixels the misfit is measured on (a regular subsample of the map: the misfit is a median over pixels)
HALO_FIT_PIXELS = 50_000


def halo_light(patterns: np.ndarray, sigma: float = HALO_SIGMA, device=None) -> torch.Tensor:
    """[N, Hp, Wp] float32 on `device`: the patterns [N, Hp, Wp] Gaussian-blurred by `sigma` projector px, edges
    replicated: the halo alone (with_halo's blur), on a GPU blurred there, on the host by OpenCV."""
    dev = _device(device)
    pats = np.asarray(patterns, np.float32)
    if dev.type == "cuda":
        return blur_patterns(torch.as_tensor(pats, device=dev), sigma)
    return torch.as_tensor(with_halo(pats, 1.0, sigma))


def fit_halo(depth: np.ndarray, camera, projector, images, patterns: np.ndarray, sigma: float = HALO_SIGMA,
             shares=HALO_SHARES, device=None, halo: torch.Tensor | None = None) -> tuple[float, dict]:
    """(share, fit) of the halo under which the pattern model best explains images [N, H, W] at depth [H, W] (mm,
    NaN: none) with patterns [N, Hp, Wp] in [0, 1] (unblurred, no halo): the pattern model's misfit
    (`model_misfit`, blur per projector depth fitted for each share) at the shares of `shares` (ascending, from 0)
    up to the first that does not lower it, the minimum refined by a parabola through its neighbours, and 0 unless it
    lowers the misfit by HALO_MIN_GAIN of the misfit without a halo. fit: {"sigma_px", "shares" (those evaluated),
    "misfits", "share"}. (0, fit) when too few pixels have depth. halo: `halo_light` of the patterns when the caller
    has it."""
    d = np.asarray(depth, np.float32)
    has = np.isfinite(d)
    step = max(1, int(np.ceil(np.sqrt(has.sum() / HALO_FIT_PIXELS))))
    if step > 1:  # a regular subsample: every step-th row and column
        keep = np.zeros_like(has)
        keep[::step, ::step] = True
        d = np.where(keep, d, np.nan).astype(np.float32)
    pats = np.asarray(patterns, np.float32)
    # blurring is linear: the ladder of (1 - s) P + s H is (1 - s) ladder(P) + s ladder(H), two ladders for all shares
    dev = _device(device)
    wide = halo_light(pats, sigma, dev) if halo is None else halo
    sharp, wide = _BlurLadder(pats, dev), _BlurLadder(wide, dev)
    shares = [float(s) for s in shares]
    misfits: list[float] = []
    # upwards from no halo while the misfit falls (it has one minimum over these shares): a lens without a halo
    # costs two evaluations, the real captures' (0.06-0.1) three to five
    for s in shares:
        ladder = copy.copy(sharp)
        ladder.rungs = (1.0 - s) * sharp.rungs + s * wide.rungs
        model = _fit_model(d, camera, projector, images, None, device, ladder=ladder)
        misfits.append(float("nan") if model is None else _misfit(model))
        if not np.isfinite(misfits[-1]) or (len(misfits) > 1 and misfits[-1] >= misfits[-2]):
            break
    shares = shares[: len(misfits)]
    fit = {"sigma_px": float(sigma), "shares": shares, "misfits": misfits, "share": 0.0}
    m = np.asarray(misfits, np.float64)
    if not np.isfinite(m).all() or 0.0 not in shares:
        return 0.0, fit
    i = int(np.argmin(m))
    share = shares[i]
    if 0 < i < len(m) - 1:  # the parabola's vertex through the minimum and its neighbours (an even grid)
        den = m[i - 1] - 2 * m[i] + m[i + 1]
        if den > 0:
            share += 0.5 * (m[i - 1] - m[i + 1]) / den * (shares[i + 1] - shares[i])
    if m[i] > (1.0 - HALO_MIN_GAIN) * m[shares.index(0.0)]:
        share = 0.0
    fit["share"] = float(share)
    return float(share), fit
