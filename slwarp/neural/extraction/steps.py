"""Ramps across a depth step split into the two surfaces, pixel by pixel as their codes fit (`split_ramps`).

Why: where a surface stands a few projector rows before another (the real captures' plate 12-54 mm before the wall
at 1.6 m: 3-12 projector rows), the codes of 7 Gray code images change only at stripe edges 8 rows apart, so inside a
stripe a smooth field may bend from one surface to the other without changing a code. The hash-grid fields draw such
steps as ramps 20-40 px wide on each side (the twin of capture 0: within 20 px of a step `fast` errs 0.9-5.8 mm where
GC(7) errs 0.3-2.1; docs/accuracy.md, section 35). The extraction's edge stages act on jumps between neighbours, and a
ramp has none.

How: along each image axis, a line is fitted to the depths on each side of a pixel, `radius` to `radius + SIDE_PX`
pixels away; where both fits are good and their extrapolations to the pixel are more than `footprints` pixel
footprints apart and the pixel's depth lies between them, more than MIN_OFF_FOOTPRINTS footprints and MIN_STEP_SHARE
of the step from each, the pixel is on a ramp between two surfaces (a depth on a line, beyond both or close to one is
a surface's own: a step drawn sharp, a fold, a curve near a silhouette). Each surface's line is then tried over a
window of the pixel's neighbours along that axis (2 WINDOW_PX + 1 pixels: a window sees the stripe edges a single
pixel cannot) against the depths the map has there, by the pattern model's residual (`pattern_model.residual_at`);
the pixel takes the line that fits best when its mean residual is at most `margin` times that of the map's own
depths.
"""
from __future__ import annotations

import numpy as np
import torch

from ..pattern_model import residual_at
from .state import ModelInputs

__all__ = ["split_ramps", "side_lines", "SIDE_PX", "WINDOW_PX", "FIT_FOOTPRINTS", "MIN_OFF_FOOTPRINTS",
           "MIN_STEP_SHARE"]

SIDE_PX = 16  # pixels each side's line is fitted to
WINDOW_PX = 6  # half-width of the window over which a line is tried (pixels)
FIT_FOOTPRINTS = 1.0  # a side's line is used when its RMS residual is at most this many pixel footprints
MIN_OFF_FOOTPRINTS = 2.0  # a pixel closer than this many pixel footprints to either line is on that surface
MIN_STEP_SHARE = 0.05  # ... and so is one closer to a line than this share of the step between the lines
_CHUNK = 2_000_000  # (pixel, depth) pairs per residual call


def _shifted(x: torch.Tensor, k: int, axis: int) -> torch.Tensor:
    """[H, W]: out[p] = x[p + k e_axis], NaN where that falls outside the image."""
    out = torch.full_like(x, float("nan"))
    n = x.shape[axis]
    if abs(k) >= n:
        return out
    src = x.narrow(axis, max(k, 0), n - abs(k))
    out.narrow(axis, max(-k, 0), n - abs(k)).copy_(src)
    return out


def side_lines(depth: torch.Tensor, axis: int, side: int, start: int, length: int = SIDE_PX):
    """(a, b, rms, n), each [H, W] float64: the line z = a + b t (t: pixels along `axis` from the pixel, z mm) fitted by
    least squares to the finite depths at t = side * (start, ..., start + length - 1) (side +1 or -1), its RMS
    residual (mm) and the number of depths it was fitted to (a, b, rms NaN below two)."""
    d = depth.double()
    s0 = torch.zeros_like(d)
    st, stt, sz, stz = s0.clone(), s0.clone(), s0.clone(), s0.clone()
    for k in range(start, start + length):
        t = float(side * k)
        z = _shifted(d, side * k, axis)
        ok = torch.isfinite(z)
        z = torch.where(ok, z, torch.zeros_like(z))
        w = ok.double()
        s0 += w
        st += w * t
        stt += w * t * t
        sz += z
        stz += z * t
    den = s0 * stt - st * st
    enough = (s0 >= 2) & (den > 0)
    den = torch.where(enough, den, torch.ones_like(den))
    b = (s0 * stz - st * sz) / den
    a = (sz - b * st) / torch.clamp(s0, min=1.0)
    ss = torch.zeros_like(d)  # the residuals in a second pass: no cancellation between large sums
    for k in range(start, start + length):
        z = _shifted(d, side * k, axis)
        r = z - a - b * float(side * k)
        ss += torch.where(torch.isfinite(r), r * r, torch.zeros_like(r))
    rms = torch.sqrt(ss / torch.clamp(s0, min=1.0))
    nan = torch.full_like(d, float("nan"))
    return torch.where(enough, a, nan), torch.where(enough, b, nan), torch.where(enough, rms, nan), s0


def _residuals(index: torch.Tensor, depths: torch.Tensor, inputs: ModelInputs) -> torch.Tensor:
    """[P] float32: `residual_at` of pixels index [P] at depths [P] mm, NaN where a depth is not finite and above 0;
    in chunks of _CHUNK pairs."""
    r = torch.full((index.numel(),), float("nan"), dtype=torch.float32, device=index.device)
    sel = torch.nonzero(torch.isfinite(depths) & (depths > 0)).squeeze(1)
    for lo in range(0, sel.numel(), _CHUNK):
        s = sel[lo: lo + _CHUNK]
        r[s] = residual_at(index[s], depths[s], *inputs.model).float()
    return r


def _window_residuals(pix: torch.Tensor, lines: list[tuple[torch.Tensor, torch.Tensor]], own: torch.Tensor,
                      axis: int, shape, inputs: ModelInputs) -> torch.Tensor:
    """[len(lines) + 1, P]: the mean pattern-model residual over each pixel's window along `axis` (offsets -WINDOW_PX
    .. WINDOW_PX, the pixels with a depth in `own` [H*W]) of each line (a, b) [P] and, last, of own's depths."""
    H, W = shape
    y, x = pix // W, pix % W
    idx, depths, use = [], [], []
    for j in range(-WINDOW_PX, WINDOW_PX + 1):
        yy, xx = (y + j, x) if axis == 0 else (y, x + j)
        inside = (yy >= 0) & (yy < H) & (xx >= 0) & (xx < W)
        q = torch.where(inside, yy * W + xx, torch.zeros_like(yy))
        idx.append(q)
        use.append(inside & torch.isfinite(own[q]))
        depths.append(torch.stack([(a + b * j).float() for a, b in lines]))
    q, use = torch.stack(idx), torch.stack(use)  # [2w + 1, P]
    z = torch.stack(depths)  # [2w + 1, lines, P]
    z = torch.where(use[:, None], z, torch.full_like(z, float("nan")))
    r_lines = _residuals(q[:, None].expand_as(z).reshape(-1), z.reshape(-1), inputs).reshape(z.shape)
    # the map's own depths: each window pixel's residual once, however many windows hold it
    mine = torch.unique(q[use])
    r_map = torch.full_like(own, float("nan"))
    r_map[mine] = _residuals(mine, own[mine], inputs)
    r_own = r_map[q]
    r_own = torch.where(use, r_own, torch.full_like(r_own, float("nan")))
    r = torch.cat([r_lines, r_own[:, None]], dim=1)  # [2w + 1, lines + 1, P]
    ok = torch.isfinite(r)
    total = torch.where(ok, r, torch.zeros_like(r)).sum(0)
    count = ok.sum(0)
    return torch.where(count > 0, total / torch.clamp(count, min=1), torch.full_like(total, float("inf")))


def split_ramps(depth: np.ndarray, inputs: ModelInputs, radius: int, footprints: float,
                margin: float) -> tuple[np.ndarray, np.ndarray]:
    """(depth [H, W] mm, switched [H, W] bool): each pixel between two surfaces along an image axis (see the module
    docstring: side lines `radius` to radius + SIDE_PX px away whose values at the pixel differ by more than
    `footprints` pixel footprints, each fitted within FIT_FOOTPRINTS footprints) given the value of the side line
    whose codes fit its window best, where that window's mean residual is at most `margin` times the map's own;
    the vertical axis first, then the horizontal one on its result. Pixels without depth stay so."""
    d = np.asarray(depth, np.float32)
    switched = np.zeros(d.shape, bool)
    if radius <= 0 or not np.isfinite(d).any():
        return d.copy(), switched
    dev = inputs.patterns.device if isinstance(inputs.patterns, torch.Tensor) else torch.device("cpu")
    f = min(inputs.camera.fx, inputs.camera.fy)
    cur = torch.as_tensor(d, device=dev).clone()
    for axis in (0, 1):
        sides = [side_lines(cur, axis, s, radius) for s in (-1, 1)]
        foot = cur.double() / f
        ok = torch.isfinite(cur)
        for a, b, rms, n in sides:
            ok &= (n >= SIDE_PX // 2) & (rms <= FIT_FOOTPRINTS * foot)
        ok &= (sides[0][0] - sides[1][0]).abs() > footprints * foot
        # a ramp lies between the two lines, on neither: a pixel on one of them (a step the field drew sharp) or
        # beyond both (a bump, a fold) is left alone, and so is one within MIN_STEP_SHARE of the step from a line (a
        # curved surface's extrapolation misses by a few per cent of a step to another surface)
        za, zb, own = sides[0][0], sides[1][0], cur.double()
        off = torch.minimum((own - za).abs(), (own - zb).abs())
        ok &= ((own - za) * (own - zb) < 0) & (off > MIN_OFF_FOOTPRINTS * foot)
        ok &= off >= MIN_STEP_SHARE * (za - zb).abs()
        pix = torch.nonzero(ok.reshape(-1)).squeeze(1)
        if pix.numel() == 0:
            continue
        lines = [(s[0].reshape(-1)[pix], s[1].reshape(-1)[pix]) for s in sides]
        flat = cur.reshape(-1)
        r = _window_residuals(pix, lines, flat, axis, cur.shape, inputs)
        best = torch.argmin(r[:2], dim=0)
        r_best = torch.gather(r[:2], 0, best[None])[0]
        take = torch.isfinite(r_best) & (r_best <= margin * r[2])
        a_best = torch.where(best == 0, lines[0][0], lines[1][0]).float()
        changed = pix[take]
        new = flat.clone()
        new[changed] = a_best[take]
        cur = new.reshape(cur.shape)
        switched.reshape(-1)[changed.cpu().numpy()] = True
    return cur.cpu().numpy().astype(np.float32), switched
