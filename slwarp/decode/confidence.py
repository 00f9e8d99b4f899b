"""Per-pixel confidence of a classical decoding, the analogue of the neural method's (slwarp.neural.extraction.confidence).

    confidence = code certainty x signal swing, in [0, 1] (1 = trustworthy)

- signal swing: 2 x the pixel's on/off amplitude (Gray code: half of white - black, `gray.Binarized.amplitude`)
  or phase modulation B (I_k = A + B cos(phi - d_k)), the smallest over the sets and axes used: the fraction of
  the full scale (images in [0, 1]) that the codes swing by. Noise moves a stripe crossing or a phase by
  about noise / swing, so a dark or low-contrast pixel is less certain.
- code certainty (methods with Gray code bits): the smallest |bit signal| / amplitude over the bits that do not
  flip at the decoded stripe's own two boundaries (`code_certainty`), clipped to 1. A bit that flips there is
  uncertain near the boundary by nature and costs nothing (interpolation and phase unwrapping handle it); a
  weak bit elsewhere means the stripe itself may be wrong.

Measured (bench/confidence.py, small rig, six scenes; AUSE against the oracle): the swing is what ranks the
errors of every method; the certainty alone ranks worse than the swing on every scene and method; their product
is slightly better than the swing for GC(6)/GC(7)-interp (GC(7) bunny 0.151 vs 0.154 mm) and within 0.01 mm of
it for CGC (whose errors are the phase's, ranked by the swing).
"""
from __future__ import annotations

import numpy as np

__all__ = ["code_certainty", "signal_swing", "decoding_confidence"]


def code_certainty(signal: np.ndarray, stripe: np.ndarray, flips: np.ndarray) -> np.ndarray:
    """[H, W] in [0, 1]: min |signal_k| over the bits k that do not flip at either boundary of the pixel's
    decoded stripe, clipped to 1 (1 where every bit flips there; NaN where the stripe is invalid).

    signal [n, H, W]: the bits' evidence (+-1 fully on/off, `gray.Binarized.signal`); stripe [H, W] int (-1
    invalid); flips [S, n] bool: the bits that differ between stripe s - 1 and s (`gray.GrayTable.flips`)."""
    n_stripes = flips.shape[0]
    s = np.clip(stripe, 0, n_stripes - 1)
    nxt = np.clip(stripe + 1, 0, n_stripes - 1)
    at_boundary = flips[s] | np.where((stripe + 1 < n_stripes)[..., None], flips[nxt], False)  # [H, W, n]
    weak = np.where(np.moveaxis(at_boundary, -1, 0), np.inf, np.abs(signal)).min(axis=0)
    return np.where(stripe >= 0, np.minimum(weak, 1.0), np.nan)


def signal_swing(amplitude: np.ndarray) -> np.ndarray:
    """[H, W] in [0, 1]: 2 x amplitude (half the on/off difference, or the phase modulation, full-scale units)."""
    return np.clip(2.0 * np.asarray(amplitude, np.float64), 0.0, 1.0)


def decoding_confidence(dec, depth: np.ndarray | None = None) -> np.ndarray:
    """[H, W] float32 confidence of a `Decoding` (see the module docstring), NaN where its coordinates (or
    `depth`, when given) are invalid. Uses the diagnostics the methods leave in dec.extra: 'certainty_{axis}' or
    'certainty' (Gray code bits), 'amplitude_{axis}' or 'amplitude' (Gray code), 'modulation' (phase)."""
    ex = dec.extra
    swings = [ex[k] for k in ("amplitude_col", "amplitude_row", "amplitude", "modulation") if k in ex]
    if not swings:
        raise ValueError(f"decoding of method {dec.method} carries no amplitude or modulation to rate its pixels by")
    conf = signal_swing(np.minimum.reduce([np.asarray(s, np.float64) for s in swings]))
    certainties = [ex[k] for k in ("certainty_col", "certainty_row", "certainty") if k in ex]
    if certainties:
        conf = conf * np.fmin.reduce([np.asarray(c, np.float64) for c in certainties])
    invalid = ~dec.valid if depth is None else ~(dec.valid & np.isfinite(depth))
    return np.where(invalid, np.nan, conf).astype(np.float32)
