"""Projector pattern sets: the paper's random multi-scale binary squares and the classical codes.

Every generator returns a `PatternSet`: `patterns` [N, H, W] float32 in [0, 1] in projector pixels
(pixel (u, v) = column, row; centre of pixel (0, 0) at (0, 0)) and one frame name per pattern. The names are
slwarp's role names (`slwarp.scans.roles.FrameRole.name`), so a simulated scan knows each frame's role, and
writes it to scan.yaml:

    rand{size}_{i}          random binary squares of `size` px, i-th pattern of that scale
    gc_{col|row}_b{k}       Gray code bit k, k = 0 the most significant bit
    gc_{col|row}_b{k}_inv   its inverse
    white, black            full-on and full-off frames
    ps_{col|row}_p{P}_s{k}of{N}   N-step phase shift with period P px, step k:
                            0.5 + 0.5 cos(2 pi u / P - 2 pi k / N)
    design{K}_{i}           i-th of K optimised grey-level patterns (`designed_names`; stored as a pattern-set
                            file: slwarp.scans.pattern_files)

Gray code with n bits cuts the axis into 2^n stripes of W / 2^n px (10 px for 7 bits on 1280 columns);
pixel u lies in stripe floor(u 2^n / W) and bit k is bit (n-1-k) of that stripe's Gray code g = s ^ (s >> 1).
The first m bits of an n-bit code are themselves the m-bit code, so any prefix of bits decodes.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .roles import FrameRole, resolve_roles

__all__ = [
    "PatternSet",
    "random_binary",
    "gray_code",
    "white_black",
    "phase_shift",
    "complementary_gray_code",
    "hierarchical_pmp",
    "number_theoretic_pmp",
    "ground_truth_set",
    "named_set",
    "NAMED_SETS",
    "designed_names",
    "gray_to_binary",
    "binary_to_gray",
]


@dataclass
class PatternSet:
    """patterns [N, H, W] float32 in [0, 1] and their frame names.

    roles: declared roles, frame name -> role (a FrameRole, a scan.yaml mapping or a role string), for frames
    whose names follow no slwarp contract (the others take their name's role; see slwarp.scans.roles); a
    simulated scan writes them to scan.yaml. source: the pattern-set file it was read from, if any (errors name it).
    """

    patterns: np.ndarray
    names: list[str]
    roles: dict | None = None
    source: str | None = field(default=None, compare=False)

    def __post_init__(self):
        self.patterns = np.asarray(self.patterns, dtype=np.float32)
        if self.patterns.ndim != 3 or len(self.names) != self.patterns.shape[0]:
            raise ValueError(f"PatternSet: {self.patterns.shape} patterns for {len(self.names)} names")
        if len(set(self.names)) != len(self.names):
            raise ValueError(f"PatternSet: duplicate frame names in {self.names}")
        if self.roles:
            stray = sorted(set(self.roles) - set(self.names))
            if stray:
                raise ValueError(f"PatternSet: roles for frames it does not have: {stray}")
            resolve_roles(self.names, self.roles)  # RoleError (a ValueError) naming the frame

    def __len__(self) -> int:
        return len(self.names)

    def __add__(self, other: "PatternSet") -> "PatternSet":
        dup = [n for n in other.names if n in self.names]
        other = other.subset([n for n in other.names if n not in dup])  # a combined set keeps one copy
        roles = {**(self.roles or {}), **(other.roles or {})} or None
        return PatternSet(np.concatenate([self.patterns, other.patterns]), self.names + other.names, roles)

    def subset(self, names: list[str]) -> "PatternSet":
        idx = [self.names.index(n) for n in names]
        roles = {n: r for n, r in (self.roles or {}).items() if n in names} or None
        return PatternSet(self.patterns[idx], list(names), roles, source=self.source)

    def frame_roles(self) -> list[FrameRole | None]:
        """[N] the role of each frame: declared (`roles`) or from its name; None where it has none."""
        return resolve_roles(self.names, self.roles)

    @property
    def width(self) -> int:
        return int(self.patterns.shape[2])

    @property
    def height(self) -> int:
        return int(self.patterns.shape[1])


def random_binary(width: int, height: int, scales=(20, 10, 5), per_scale: int = 2, seed: int = 0) -> PatternSet:
    """The paper's random multi-scale binary patterns.

    The projector plane is cut into squares of each size (aligned at pixel 0), each square black or white
    with probability 1/2. Order: one pattern of each scale in turn (20, 10, 5, 20, 10, 5, ...), so that any
    prefix (as in incremental training) covers all scales as early as possible.
    """
    rng = np.random.default_rng(seed)
    pats, names = [], []
    for i in range(per_scale):
        for s in scales:
            cells = rng.integers(0, 2, size=(math.ceil(height / s), math.ceil(width / s)))
            img = np.repeat(np.repeat(cells, s, axis=0), s, axis=1)[:height, :width]
            pats.append(img.astype(np.float32))
            names.append(FrameRole("random", size=float(s), index=i).name)
    return PatternSet(np.stack(pats), names)


def binary_to_gray(b):
    return b ^ (b >> 1)


def gray_to_binary(g):
    """Inverse of g = b ^ (b >> 1) for integer arrays (any width up to 32 bits)."""
    b = np.array(g, dtype=np.int64, copy=True)
    shift = 1
    while shift < 32:
        b ^= b >> shift
        shift *= 2
    return b


def stripe_index(coord: np.ndarray, size: int, bits: int) -> np.ndarray:
    """Stripe of integer pixel coordinate(s) along an axis of `size` px in an n-bit code."""
    return (np.asarray(coord, dtype=np.int64) * (1 << bits)) // size


def gray_code(width: int, height: int, bits: int, axis: str = "col", inverse: bool = False) -> PatternSet:
    """Gray code over columns (axis='col') or rows ('row'), most significant bit first.

    White (1) where the bit is set. With `inverse`, each bit is followed by its inverse.
    """
    if axis not in ("col", "row"):
        raise ValueError(f"axis must be 'col' or 'row', got {axis!r}")
    size = width if axis == "col" else height
    if bits < 1 or (1 << bits) > 4 * size:
        raise ValueError(f"{bits} Gray code bits do not fit {size} projector pixels")
    g = binary_to_gray(stripe_index(np.arange(size), size, bits))
    pats, names = [], []
    for k in range(bits):
        bit = ((g >> (bits - 1 - k)) & 1).astype(np.float32)
        img = np.broadcast_to(bit[None, :], (height, width)) if axis == "col" else np.broadcast_to(bit[:, None], (height, width))
        pats.append(np.array(img))
        names.append(FrameRole("gray", axis=axis, bit=k).name)
        if inverse:
            pats.append(1.0 - pats[-1])
            names.append(FrameRole("gray", axis=axis, bit=k, inverse=True).name)
    return PatternSet(np.stack(pats), names)


def white_black(width: int, height: int) -> PatternSet:
    return PatternSet(np.stack([np.ones((height, width), np.float32), np.zeros((height, width), np.float32)]),
                      [FrameRole("white").name, FrameRole("black").name])


def phase_shift(width: int, height: int, period: float, steps: int, axis: str = "col") -> PatternSet:
    """N-step phase shifting: 0.5 + 0.5 cos(2 pi u / period - 2 pi k / steps), k = 0..steps-1."""
    if steps < 3:
        raise ValueError("phase shifting needs at least 3 steps")
    if period <= 0:
        raise ValueError("period must be positive")
    size = width if axis == "col" else height
    coord = np.arange(size, dtype=np.float64)
    pats, names = [], []
    for k in range(steps):
        prof = 0.5 + 0.5 * np.cos(2 * np.pi * coord / period - 2 * np.pi * k / steps)
        img = np.broadcast_to(prof[None, :], (height, width)) if axis == "col" else np.broadcast_to(prof[:, None], (height, width))
        pats.append(np.array(img, dtype=np.float32))
        names.append(FrameRole("phase", axis=axis, period=float(period), step=k, steps=steps).name)
    return PatternSet(np.stack(pats), names)


def _axis_size(width: int, height: int, axis: str) -> int:
    if axis not in ("col", "row"):
        raise ValueError(f"axis must be 'col' or 'row', got {axis!r}")
    return width if axis == "col" else height


def complementary_gray_code(width: int, height: int, gray_bits: int = 3, steps: int = 3, axis: str = "col") -> PatternSet:
    """CGC: `gray_bits` Gray code patterns + `steps`-step phase shift with period S / 2^(gray_bits - 1), S the
    projector width (axis 'col') or height ('row').

    The Gray code's last bit splits each phase period in half; it corrects the period-edge jumps.
    The paper's 6-pattern set is (3, 3), the 7-pattern set (4, 3).
    """
    period = _axis_size(width, height, axis) / (1 << (gray_bits - 1))
    return gray_code(width, height, gray_bits, axis) + phase_shift(width, height, period, steps, axis)


def hierarchical_pmp(width: int, height: int, short_period: float = 80.0, steps: int = 3, axis: str = "col") -> PatternSet:
    """H-PMP: one `steps`-step set with a single period across the axis, one with a short period."""
    size = float(_axis_size(width, height, axis))
    return phase_shift(width, height, size, steps, axis) + phase_shift(width, height, short_period, steps, axis)


def number_theoretic_pmp(width: int, height: int, periods=(48, 70), steps: int = 3, axis: str = "col") -> PatternSet:
    """N-PMP: two `steps`-step sets with integer periods, co-prime in units of their greatest common
    divisor, whose least common multiple (the unambiguous range) covers the axis: 48 and 70 px -> 1680 px."""
    p1, p2 = (int(p) for p in periods)
    g = math.gcd(p1, p2)
    size = _axis_size(width, height, axis)
    if g in (p1, p2):
        raise ValueError(f"N-PMP periods must be co-prime (in units of their gcd), got {p1} and {p2}")
    if p1 * p2 // g < size:
        raise ValueError(f"N-PMP periods {p1}, {p2} are unambiguous over only {p1 * p2 // g} px < {size} px")
    return phase_shift(width, height, p1, steps, axis) + phase_shift(width, height, p2, steps, axis)


def designed_names(count: int) -> list[str]:
    """The frame names of a designed (optimised) set of `count` patterns: design{count}_0 .. design{count}_{count-1}
    (role {kind: designed, index: i, count: count})."""
    if int(count) < 1:
        raise ValueError(f"a designed pattern set has at least 1 pattern, got count={count}")
    return [FrameRole("designed", index=i, count=int(count)).name for i in range(int(count))]


def ground_truth_set(width: int, height: int, axis: str = "col") -> PatternSet:
    """7 Gray code patterns with inverses + 4-step phase shift with a 40 px period (18 patterns)."""
    return gray_code(width, height, 7, axis, inverse=True) + phase_shift(width, height, 40.0, 4, axis)


# ----------------------------------------------------------------------------------------------
# Named sets (CLI): a name, or several joined with '+', e.g. "random6+gray7+gt".

NAMED_SETS = {
    "randomN": "the paper's random binary squares of 20, 10, 5 px, N/3 per scale (random6 = paper, random9)",
    "grayN": "N-bit column Gray code, no inverses (gray6, gray7, ...)",
    "grayNinv": "N-bit column Gray code, each bit followed by its inverse (gray7inv: 14 patterns)",
    "grayrowN / grayrowNinv": "the same over projector rows",
    "whiteblack": "all-white and all-black frames",
    "psN": "N-step phase shift with one period across the width",
    "cgc6 / cgc7": "complementary Gray code: 3 (4) Gray code bits + 3-step phase shift, period W/4 (W/8)",
    "hpmp6": "hierarchical PMP: 3-step at period W + 3-step at 80 px",
    "npmp6": "number-theoretic PMP: 3-step at 48 px + 3-step at 70 px",
    "gt": "ground truth set: gray7inv + 4-step phase shift, period 40 px (18 patterns)",
    "NAME_row": "any of these codes over the projector rows instead of its columns (gt_row, npmp6_row, cgc7_row; "
                "periods W become H)",
    "FILE": "a pattern-set file, PATH/patterns.yaml or its folder: e.g. a set written by `slwarp design-patterns` "
            "(its size must be the projector's)",
}


def _one_named(name: str, width: int, height: int, seed: int) -> PatternSet:
    axis = "col"
    if name.endswith("_row"):
        name, axis = name[: -len("_row")], "row"
        if name.startswith(("random", "whiteblack", "grayrow")):
            raise ValueError(f"pattern set {name}_row: '_row' applies to the coded sets (gray, ps, cgc, hpmp, npmp, gt)")
    m = re.fullmatch(r"random(\d+)", name)
    if m:
        n = int(m.group(1))
        if n < 3 or n % 3:
            raise ValueError(f"pattern set {name!r}: randomN needs N a positive multiple of 3 (one per scale)")
        return random_binary(width, height, per_scale=n // 3, seed=seed)
    m = re.fullmatch(r"gray(row)?(\d+)(inv)?", name)
    if m:
        return gray_code(width, height, int(m.group(2)), axis="row" if m.group(1) else axis, inverse=bool(m.group(3)))
    m = re.fullmatch(r"ps(\d+)", name)
    if m:
        return phase_shift(width, height, float(_axis_size(width, height, axis)), int(m.group(1)), axis)
    fixed = {
        "whiteblack": lambda: white_black(width, height),
        "cgc6": lambda: complementary_gray_code(width, height, 3, axis=axis),
        "cgc7": lambda: complementary_gray_code(width, height, 4, axis=axis),
        "hpmp6": lambda: hierarchical_pmp(width, height, axis=axis),
        "npmp6": lambda: number_theoretic_pmp(width, height, axis=axis),
        "gt": lambda: ground_truth_set(width, height, axis=axis),
    }
    if name in fixed:
        return fixed[name]()
    raise ValueError(f"unknown pattern set {name!r}; known: " + ", ".join(NAMED_SETS))


def _from_file(path: str, width: int, height: int) -> PatternSet:
    """The pattern-set file `path` (slwarp.scans.pattern_files), which must be the projector's size."""
    from .pattern_files import read_pattern_set

    pset = read_pattern_set(path)
    if (pset.width, pset.height) != (width, height):
        raise ValueError(f"{pset.source}: the pattern set is {pset.width}x{pset.height}, the projector "
                         f"{width}x{height}")
    return pset


def _one_part(part: str, width: int, height: int, seed: int) -> PatternSet:
    from .pattern_files import is_pattern_set_path

    if is_pattern_set_path(part):
        return _from_file(part, width, height)
    if "/" in part or "\\" in part:  # meant as a path: say so rather than "unknown pattern set"
        raise ValueError(f"{part}: no pattern-set file there (need PATH/patterns.yaml, a .yaml file, or a folder "
                         "holding patterns.yaml)")
    return _one_named(part, width, height, seed)


def named_set(spec: str, width: int, height: int, seed: int = 0) -> PatternSet:
    """A named pattern set (see NAMED_SETS) or a pattern-set file, or several joined with '+' (duplicate frames
    kept once). A file must be width x height (ValueError naming it and both sizes)."""
    from .pattern_files import is_pattern_set_path

    whole = spec.strip()
    if is_pattern_set_path(whole) and ("+" not in whole or Path(whole).exists()):  # a file name may hold a '+'
        return _from_file(whole, width, height)
    parts = [p.strip() for p in spec.split("+") if p.strip()]
    if not parts:
        raise ValueError("empty pattern set name")
    out = _one_part(parts[0], width, height, seed)
    for p in parts[1:]:
        out = out + _one_part(p, width, height, seed)
    return out
