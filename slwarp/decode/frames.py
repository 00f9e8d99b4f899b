"""Which frames of a scan the decoders use, read from the scan's frame roles (`Scan.roles`, see
`slwarp.scans.roles`): Gray code bits and their inverses, phase-shift sets, and uniform frames (white, black,
other levels) that give the per-pixel threshold and amplitude.

Decoders never guess a role from a frame's name, its order or its image content; a method whose frames are
missing raises `MissingFrames`, whose message says what the method needs and what the scan has. What the
pattern images themselves determine is read from them: the Gray code's stripes (`gray.GrayTable`), each
phase-shift frame's shift (`measure_phase_shifts`), each uniform frame's level.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..scans.roles import describe_roles

__all__ = ["DEFAULT_MIN_AMPLITUDE", "MissingFrames", "GrayFrames", "LitReference", "PhaseSet", "gray_frames",
           "lit_reference", "phase_sets", "measure_phase_shifts", "axis_size"]

# Shadow threshold shared by every decoder: the pixel's on/off amplitude (half of white - black) or phase
# modulation, in full-scale units (images in [0, 1]). 0.03 is ~8 grey levels of 255 (white - black >= 15),
# about 3x the simulator's noise at mid grey; lit surfaces facing the projector have 0.1 to 0.3.
DEFAULT_MIN_AMPLITUDE = 0.03


class MissingFrames(ValueError):
    """A decoding method's frames are not in the scan. The message names the roles it needs and lists the
    scan's frames by role."""

    def __init__(self, method: str, needs: str, scan):
        self.method, self.needs, self.names = method, needs, list(scan.names)
        super().__init__(f"method {method} needs {needs}; the scan has: {describe_roles(scan.names, scan.roles)}")


def axis_size(scan, axis: str) -> int:
    """Projector pixels along `axis`: the width for column codes, the height for row codes."""
    return scan.projector.width if axis == "col" else scan.projector.height


@dataclass
class LitReference:
    """Per-pixel threshold and amplitude of a binary pattern, from uniform frames: threshold [H, W] = the image
    a pattern of level 0.5 would give, amplitude [H, W] = half the on/off difference (full-scale units);
    names: the frames used."""

    threshold: np.ndarray
    amplitude: np.ndarray
    names: list[str]


def lit_reference(scan, min_level_gap: float = 0.25) -> LitReference | None:
    """The threshold and amplitude from the scan's uniform frames (roles white, black, uniform), or None.

    Each frame's level is its pattern's mean (0 = black, 1 = white). The two frames whose levels differ the
    most (by at least `min_level_gap`) give, under the linear image model I = A + B level, the threshold
    A + B / 2 and the amplitude B / 2; with white and black that is (white + black) / 2 and (white - black) / 2.
    """
    idx = [i for i, r in enumerate(scan.roles) if r is not None and r.kind in ("white", "black", "uniform")]
    if len(idx) < 2:
        return None
    levels = np.array([float(scan.patterns[i].mean()) for i in idx])
    hi, lo = int(np.argmax(levels)), int(np.argmin(levels))
    gap = levels[hi] - levels[lo]
    if gap < min_level_gap:
        return None
    i_hi, i_lo = scan.images[idx[hi]].astype(np.float64), scan.images[idx[lo]].astype(np.float64)
    slope = (i_hi - i_lo) / gap  # image per unit of pattern level: B
    return LitReference(i_lo + (0.5 - levels[lo]) * slope, 0.5 * slope, [scan.names[idx[hi]], scan.names[idx[lo]]])


@dataclass
class GrayFrames:
    """The Gray code frames of one axis: `bits` consecutive bits from bit 0, with or without inverses.

    names: the bit frames' names; images [n, H, W] and patterns [n, Hp, Wp] of the bit frames;
    inverse_names / inverse_images [n, H, W] or None; lit: threshold and amplitude from uniform frames or None.
    """

    axis: str
    names: list[str]
    images: np.ndarray
    patterns: np.ndarray
    inverse_names: list[str] | None
    inverse_images: np.ndarray | None
    lit: LitReference | None

    @property
    def bits(self) -> int:
        return len(self.names)

    @property
    def used(self) -> list[str]:
        """Every frame these frames were read from (bits, inverses, uniform frames)."""
        return self.names + (self.inverse_names or []) + (self.lit.names if self.lit is not None else [])


def gray_frames(scan, axis: str = "col", bits: int | None = None, use_inverse: bool | None = None) -> GrayFrames | None:
    """The scan's Gray code frames along `axis`: the consecutive bits 0, 1, ... it holds (all of them, or the
    first `bits`), with inverses when every one of those bits has its inverse (and `use_inverse` is not
    False). None when the scan has no bit 0 along `axis`, or fewer than `bits` consecutive bits."""
    idx, inv = [], []
    while True:
        i = scan.frame_with("gray", axis=axis, bit=len(idx), inverse=False)
        if i is None:
            break
        idx.append(i)
        inv.append(scan.frame_with("gray", axis=axis, bit=len(idx) - 1, inverse=True))
    if not idx or (bits is not None and len(idx) < bits):
        return None
    n = len(idx) if bits is None else bits
    idx, inv = idx[:n], inv[:n]
    has_inv = use_inverse is not False and all(i is not None for i in inv)
    return GrayFrames(axis, [scan.names[i] for i in idx], scan.images[idx], scan.patterns[idx],
                      [scan.names[i] for i in inv] if has_inv else None, scan.images[inv] if has_inv else None,
                      lit_reference(scan))


@dataclass
class PhaseSet:
    """One complete N-step phase-shift set: images [N, H, W] in step order, period (projector px), and the
    shift of each step measured from its pattern, shifts [N] rad (pattern = a + b cos(2 pi u / P - shift))."""

    axis: str
    period: float
    steps: int
    names: list[str]
    images: np.ndarray
    shifts: np.ndarray

    def describe(self) -> str:
        return f"{self.steps}-step phase shift phase:{self.axis}:period={self.period:g}"


def phase_sets(scan, axis: str = "col") -> list[PhaseSet]:
    """Every complete phase-shift set along `axis` in the scan (all steps 0..N-1 present), in the order of
    their first frame, with each step's shift measured from its pattern (`measure_phase_shifts`)."""
    found: dict[tuple[float, int], dict[int, int]] = {}
    for i, r in enumerate(scan.roles):
        if r is not None and r.kind == "phase" and r.axis == axis:
            found.setdefault((r.period, r.steps), {})[r.step] = i
    out = []
    for (period, steps), by_step in found.items():
        if sorted(by_step) != list(range(steps)):
            continue
        ids = [by_step[k] for k in range(steps)]
        names = [scan.names[i] for i in ids]
        shifts = measure_phase_shifts(scan.patterns[ids], axis, period, names)
        out.append(PhaseSet(axis, period, steps, names, scan.images[ids], shifts))
    return out


def measure_phase_shifts(patterns: np.ndarray, axis: str, period: float, names: list[str],
                         max_residual: float = 0.05, min_modulation: float = 0.05) -> np.ndarray:
    """Shift [N] rad of each phase-shift pattern [N, Hp, Wp]: its profile along the projector `axis` (the
    middle row for column codes, the middle column for row codes) fitted by least squares with
    a + b cos(2 pi u / period - shift), u the projector px.

    So any N-step convention decodes: slwarp's (shift 2 pi k / N), the NeSS authors' (their steps run the
    other way, offset by pi), any offset. A pattern whose profile is not such a sinusoid (RMS residual above
    `max_residual` of b, or b below `min_modulation`: a wrong period, the wrong axis, a binary pattern) raises
    ValueError naming the frame; so do shifts that cannot determine a phase (fewer than 3 distinct ones)."""
    pats = np.asarray(patterns, np.float64)
    prof = pats[:, pats.shape[1] // 2, :] if axis == "col" else pats[:, :, pats.shape[2] // 2]
    w = 2 * np.pi * np.arange(prof.shape[1]) / period
    M = np.stack([np.ones_like(w), np.cos(w), np.sin(w)], 1)
    coef, *_ = np.linalg.lstsq(M, prof.T, rcond=None)  # [3, N]
    shifts = np.arctan2(coef[2], coef[1])
    b = np.hypot(coef[1], coef[2])
    rms = np.sqrt(((M @ coef - prof.T) ** 2).mean(0))
    along = "columns" if axis == "col" else "rows"
    for k, name in enumerate(names):
        if b[k] < min_modulation or rms[k] > max_residual * b[k]:
            raise ValueError(
                f"pattern of frame {name} is not a sinusoid of period {period:g} px along the projector {along} "
                f"(fitted amplitude {b[k]:.3f}, RMS residual {rms[k]:.3f}): check the role's period and axis"
            )
    D = np.stack([np.ones_like(shifts), np.cos(shifts), np.sin(shifts)], 1)
    sv = np.linalg.svd(D, compute_uv=False)
    if sv[-1] < 1e-3 * sv[0]:
        raise ValueError(f"phase-shift frames {', '.join(names)}: their patterns' shifts "
                         f"({', '.join(f'{np.degrees(s):.0f}' for s in shifts)} deg) cannot determine a phase")
    return shifts
