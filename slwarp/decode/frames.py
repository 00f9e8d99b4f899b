"""Which frames of a scan play which role, read from their names (the contract in `slwarp.scans.patterns`).

    gc_{col|row}_b{k}[_inv]          Gray code bit k (k = 0 most significant) and its inverse
    white, black                     full-on and full-off frames
    ps_{col|row}_p{P}_s{k}of{N}      N-step phase shift, period P projector px, step k

Decoders never guess a role from frame order or image content; a method whose frames are missing raises
`MissingFrames`, whose message says what the method needs and what the scan has.
"""
from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

__all__ = ["DEFAULT_MIN_AMPLITUDE", "MissingFrames", "GrayFrames", "PhaseSet", "gray_frames", "phase_sets", "axis_size", "describe_names"]

# Shadow threshold shared by every decoder: the pixel's on/off amplitude (half of white - black) or phase
# modulation, in full-scale units (images in [0, 1]). 0.03 is ~8 grey levels of 255 (white - black >= 15),
# about 3x the simulator's noise at mid grey; lit surfaces facing the projector have 0.1 to 0.3.
DEFAULT_MIN_AMPLITUDE = 0.03

_GC = re.compile(r"gc_(col|row)_b(\d+)(_inv)?")
_PS = re.compile(r"ps_(col|row)_p([0-9]*\.?[0-9]+(?:e[+-]?\d+)?)_s(\d+)of(\d+)")


class MissingFrames(ValueError):
    """A decoding method's frames are not in the scan. The message names the frames it needs."""

    def __init__(self, method: str, needs: str, names: list[str]):
        self.method, self.needs, self.names = method, needs, list(names)
        super().__init__(f"method {method} needs {needs}; the scan has: {describe_names(names)}")


def describe_names(names: list[str], limit: int = 12) -> str:
    """A compact listing of frame names: runs of one family are abbreviated (gc_col_b0..b6 (+inv))."""
    if not names:
        return "(no frames)"
    groups: dict[str, list[str]] = {}
    for n in names:
        m = _GC.fullmatch(n)
        if m:
            key = f"gc_{m.group(1)}"
        else:
            m = _PS.fullmatch(n)
            key = f"ps_{m.group(1)}_p{m.group(2)}_of{m.group(4)}" if m else n
        groups.setdefault(key, []).append(n)
    parts = []
    for key, members in groups.items():
        if key.startswith("gc_"):
            bits = sorted({int(_GC.fullmatch(n).group(2)) for n in members})
            inv = sum(1 for n in members if n.endswith("_inv"))
            rng = f"{key}_b{bits[0]}" + (f"..b{bits[-1]}" if len(bits) > 1 else "")
            if len(bits) > 1 and bits != list(range(bits[0], bits[-1] + 1)):
                rng = f"{key}_b{{{','.join(map(str, bits))}}}"
            parts.append(rng + (" (+inv)" if inv == len(bits) else f" ({inv} inverses)" if inv else ""))
        elif key.startswith("ps_"):
            m = _PS.fullmatch(members[0])
            steps = sorted(int(_PS.fullmatch(n).group(3)) for n in members)
            parts.append(f"ps_{m.group(1)}_p{m.group(2)}_s{{{','.join(map(str, steps))}}}of{m.group(4)}")
        else:
            parts.append(key if len(members) == 1 else f"{key} x{len(members)}")
    if len(parts) > limit:
        parts = parts[:limit] + [f"... ({len(names)} frames in all)"]
    return ", ".join(parts)


def axis_size(scan, axis: str) -> int:
    """Projector pixels along `axis`: the width for column codes, the height for row codes."""
    return scan.projector.width if axis == "col" else scan.projector.height


@dataclass
class GrayFrames:
    """The Gray code frames of one axis: `bits` consecutive bits from b0, with or without inverses.

    images [n, H, W] and patterns [n, Hp, Wp] of the bit frames; inverse_images [n, H, W] or None;
    white, black: [H, W] images or None.
    """

    axis: str
    names: list[str]
    images: np.ndarray
    patterns: np.ndarray
    inverse_images: np.ndarray | None
    white: np.ndarray | None
    black: np.ndarray | None

    @property
    def bits(self) -> int:
        return len(self.names)


def gray_frames(scan, axis: str = "col", bits: int | None = None, use_inverse: bool | None = None) -> GrayFrames | None:
    """The scan's Gray code frames along `axis`: the consecutive bits b0, b1, ... it holds (all of them,
    or the first `bits`), with inverses when every one of those bits has its inverse (and `use_inverse`
    is not False). None when the scan has no gc_{axis}_b0, or fewer than `bits` consecutive bits."""
    n = 0
    while f"gc_{axis}_b{n}" in scan.names:
        n += 1
    if n == 0 or (bits is not None and n < bits):
        return None
    n = n if bits is None else bits
    names = [f"gc_{axis}_b{k}" for k in range(n)]
    inv_names = [f"{nm}_inv" for nm in names]
    has_inv = all(nm in scan.names for nm in inv_names) if use_inverse is not False else False
    idx = [scan.names.index(nm) for nm in names]
    inv = scan.images[[scan.names.index(nm) for nm in inv_names]] if has_inv else None
    white = scan.image("white") if "white" in scan.names else None
    black = scan.image("black") if "black" in scan.names else None
    if white is None or black is None:
        white = black = None  # the threshold needs both
    return GrayFrames(axis, names, scan.images[idx], scan.patterns[idx], inv, white, black)


@dataclass
class PhaseSet:
    """One complete N-step phase-shift set: images [N, H, W] in step order, period (projector px)."""

    axis: str
    period: float
    steps: int
    names: list[str]
    images: np.ndarray

    def describe(self) -> str:
        return f"{self.steps}-step phase shift ps_{self.axis}_p{self.period:g}_s*of{self.steps}"


def phase_sets(scan, axis: str = "col", check_patterns: bool = True) -> list[PhaseSet]:
    """Every complete phase-shift set along `axis` in the scan (all steps 0..N-1 present), in the order
    of their first frame.

    With `check_patterns`, each pattern is compared with the contract 0.5 + 0.5 cos(2 pi u / P - 2 pi k / N)
    along one projector row (column for row codes): a mismatch would silently bias every decoded
    coordinate, so it raises ValueError naming the frame instead.
    """
    found: dict[tuple[str, int], dict[int, int]] = {}
    order: list[tuple[str, int]] = []
    for i, n in enumerate(scan.names):
        m = _PS.fullmatch(n)
        if not m or m.group(1) != axis:
            continue
        key = (m.group(2), int(m.group(4)))
        if key not in found:
            found[key] = {}
            order.append(key)
        found[key][int(m.group(3))] = i
    out = []
    for key in order:
        p_str, steps = key
        idx = found[key]
        if sorted(idx) != list(range(steps)):
            continue
        ids = [idx[k] for k in range(steps)]
        period = float(p_str)
        if check_patterns:
            _check_phase_patterns(scan, ids, axis, period, steps)
        out.append(PhaseSet(axis, period, steps, [scan.names[i] for i in ids], scan.images[ids]))
    return out


def _check_phase_patterns(scan, ids, axis, period, steps, tol: float = 0.02) -> None:
    pats = scan.patterns[ids]
    prof = pats[:, pats.shape[1] // 2, :] if axis == "col" else pats[:, :, pats.shape[2] // 2]
    u = np.arange(prof.shape[1], dtype=np.float64)
    for k in range(steps):
        expect = 0.5 + 0.5 * np.cos(2 * np.pi * u / period - 2 * np.pi * k / steps)
        err = float(np.abs(prof[k] - expect).max())
        if err > tol:
            raise ValueError(
                f"pattern of frame {scan.names[ids[k]]} does not follow the phase-shift contract "
                f"0.5 + 0.5 cos(2 pi u / {period:g} - 2 pi {k} / {steps}) (max deviation {err:.3f})"
            )
