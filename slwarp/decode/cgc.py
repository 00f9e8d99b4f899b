"""Gray code + phase shifting: complementary Gray code (CGC) and the ground-truth pipeline.

Both decode a Gray code to a stripe and unwrap a phase-shift set with it (`unwrap_with_reference`):

- CGC: n Gray code bits + a 3-step phase shift with period P = W / 2^(n - 1), so each Gray code stripe is
  half a period wide (6 patterns: n = 3, P = W/4; 7 patterns: n = 4, P = W/8). The stripe centre is within
  P/4 of the true position, so rounding to the nearest period order is right with a P/4 margin: the extra
  Gray code bit (n bits where n - 1 would number the periods) is what corrects the jumps at period edges.
- Ground truth: 7 bits with inverses (10 px stripes on 1280 columns) + a 4-step phase shift with period 40 px
  (4 stripes per period: the stripe centre is within 5 px of the true position, the margin is 15 px).

Without inverses and without uniform (white/black) frames, the Gray code threshold is the phase set's offset A
(equal to (white + black) / 2 in the image model), which is exact where (max + min) / 2 over three Gray
code images is not, and which decodes stripe 0 (all bits off).
"""
from __future__ import annotations

import numpy as np

from .frames import DEFAULT_MIN_AMPLITUDE, GrayFrames, PhaseSet
from .gray import GrayTable, binarize, decode_stripes
from .phase import unwrap_with_reference, wrapped_phase, wrapped_position

__all__ = ["decode_gray_phase"]


def decode_gray_phase(gf: GrayFrames, pset: PhaseSet, min_amplitude: float = DEFAULT_MIN_AMPLITUDE, min_bit_contrast: float = 0.0):
    """Absolute projector positions from a Gray code and a phase-shift set along the same axis.

    Returns (u [H, W] float64 projector px, NaN invalid; extra dict with 'stripe', 'modulation',
    'amplitude', 'wrapped'). A pixel is valid where its phase modulation and Gray code amplitude are both
    at least `min_amplitude` and its code names a stripe.
    """
    table = GrayTable.from_patterns(gf.patterns, gf.axis, gf.names)
    if table.max_width >= pset.period:
        raise ValueError(
            f"Gray code stripes of up to {table.max_width} px cannot unwrap a phase with period {pset.period:g} px "
            f"(they must be narrower than the period; {gf.bits} bits given)"
        )
    phi, offset, modulation = wrapped_phase(pset.images, pset.shifts)
    b = binarize(gf, min_amplitude, min_bit_contrast, reference=(offset, modulation))
    stripe, center = decode_stripes(b, table)
    u_w = wrapped_position(phi, pset.period)
    valid = (stripe >= 0) & (modulation >= min_amplitude)
    u = np.where(valid, unwrap_with_reference(u_w, center, pset.period), np.nan)
    return u, {"stripe": stripe, "modulation": modulation, "amplitude": b.amplitude, "wrapped": u_w}
