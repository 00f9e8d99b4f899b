"""The classical decoding methods, their registry, and scan -> depth reconstruction.

    decode(scan, method, frames=None, **params) -> Decoding
    reconstruct_depth(scan, method, frames=None, triangulation='auto', **params) -> (depth, points, Decoding)

Each method reads its frames by role (see `frames.py`), returns projector coordinates per camera pixel
(float64, continuous projector px, NaN where invalid) and raises `MissingFrames` when the scan lacks them.
Gray code methods decode every axis the scan has codes for; the phase methods decode one axis, by default the
one that carries depth on this rig (`triangulate.choose_plane_axis`) when the scan has its frames, else the
other.
Common parameters: min_amplitude (shadow threshold: half the on/off difference, or the phase modulation,
in full-scale units; images are in [0, 1]), min_bit_contrast (Gray code, relative; off by default).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from .cgc import decode_gray_phase
from .frames import DEFAULT_MIN_AMPLITUDE, MissingFrames, PhaseSet, axis_size, gray_frames, phase_sets
from .gray import GrayTable, binarize, decode_stripes, interpolate_stripes
from .phase import (NumberTheoreticTable, coarse_position, unwrap_number_theoretic, unwrap_with_reference,
                    wrapped_phase, wrapped_position)
from .triangulate import choose_plane_axis, triangulate

__all__ = ["Decoding", "Method", "METHODS", "decode", "reconstruct_depth", "finalize_positions"]


@dataclass
class Decoding:
    """Projector coordinates per camera pixel.

    col, row: [H, W] float64 continuous projector px (NaN invalid), or None when the method does not
    decode that axis; valid [H, W] bool: every decoded coordinate is finite; method: its name;
    frames: the frame names used; extra: diagnostics ('stripe_col', 'amplitude_col', 'how_col' (gc-interp,
    see `gray.HOW_*`), 'modulation', 'periods', 'decode_s', 'triangulation', ...).
    """

    col: np.ndarray | None
    row: np.ndarray | None
    valid: np.ndarray
    method: str
    frames: list[str] = field(default_factory=list)
    extra: dict = field(default_factory=dict)


def finalize_positions(u: np.ndarray, size: int, tol: float = 0.5) -> np.ndarray:
    """Keep positions on the projector: [-0.5, size - 0.5] (the pixel area); up to `tol` px beyond is
    clamped (noise at the edge), anything further is NaN, as is every non-finite value."""
    u = np.asarray(u, np.float64)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(u) & (u >= -0.5 - tol) & (u <= size - 0.5 + tol)
    return np.where(ok, np.clip(u, -0.5, size - 0.5), np.nan)


# ----------------------------------------------------------------------------------------------
# methods


def _gc(scan, interp: bool, min_amplitude=DEFAULT_MIN_AMPLITUDE, min_bit_contrast=0.0, fallback="extrapolate",
        bits: int | None = None):
    name = "gc-interp" if interp else "gc"
    coords, extra, used = {}, {}, []
    for axis in ("col", "row"):
        gf = gray_frames(scan, axis, bits)
        if gf is None:
            continue
        table = GrayTable.from_patterns(gf.patterns, axis, gf.names)
        b = binarize(gf, min_amplitude, min_bit_contrast)
        stripe, center = decode_stripes(b, table)
        if interp:
            # along camera rows, columns or both, as the local code gradient runs (see interpolate_stripes)
            u, how, info = interpolate_stripes(stripe, b.signal, table, fallback=fallback)
            extra[f"how_{axis}"] = how  # see slwarp.decode.gray.HOW_*
            extra[f"weight_row_{axis}"] = info["weight_row"]
        else:
            u = center
        coords[axis] = finalize_positions(u, axis_size(scan, axis))
        extra[f"stripe_{axis}"] = stripe
        extra[f"amplitude_{axis}"] = b.amplitude
        extra[f"bits_{axis}"] = gf.bits
        extra[f"inverses_{axis}"] = gf.inverse_images is not None
        used += gf.used
    if not coords:
        raise MissingFrames(name, "Gray code frames: roles gray:col:bit=0, bit=1, ... (most significant first; "
                            "optionally their inverses gray:col:inv, and white and black), or the same for rows "
                            "(slwarp names gc_col_b0, gc_col_b0_inv, ...)", scan)
    return coords.get("col"), coords.get("row"), used, extra


def _find_set(sets: list[PhaseSet], period: float, steps: int | None, rel: float = 1e-4) -> PhaseSet | None:
    """The set with this period (relative tolerance: names round periods with %g) and `steps` steps
    (None: any, the most steps first), or None."""
    hits = [s for s in sets if abs(s.period - period) <= rel * period and (steps is None or s.steps == steps)]
    return max(hits, key=lambda s: s.steps) if hits else None


def _ps(scan, axis, min_amplitude=DEFAULT_MIN_AMPLITUDE, steps=None):
    size = axis_size(scan, axis)
    sets = [s for s in phase_sets(scan, axis) if s.period >= size - 1e-6 and (steps is None or s.steps == steps)]
    if not sets:
        raise MissingFrames("ps", f"an N-step phase shift along {axis} whose period covers the projector "
                            f"{'width' if axis == 'col' else 'height'} ({size} px): roles phase:{axis}:period={size}"
                            f":steps=N, step 0..N-1 (slwarp names ps_{axis}_p{size}_s0ofN, ...; the set ps4)", scan)
    pset = max(sets, key=lambda s: (s.steps, -s.period))
    phi, _, mod = wrapped_phase(pset.images, pset.shifts)
    u = np.where(mod >= min_amplitude, coarse_position(phi, pset.period), np.nan)
    u = finalize_positions(u, size)
    return u, pset.names, {"modulation": mod, "periods": [pset.period]}


def _cgc(scan, axis, bits: int | None = None, steps: int | None = 3, min_amplitude=DEFAULT_MIN_AMPLITUDE,
         min_bit_contrast=0.0):
    size = axis_size(scan, axis)
    gf_all = gray_frames(scan, axis)
    avail = gf_all.bits if gf_all is not None else 0
    sets = phase_sets(scan, axis)
    choice = None
    for m in ([bits] if bits else range(avail, 1, -1)):
        if m > avail:
            break
        pset = _find_set(sets, size / (1 << (m - 1)), steps)
        if pset is not None:
            choice = (m, pset)
            break
    if choice is None:
        m = bits or 3
        W = "W" if axis == "col" else "H"
        raise MissingFrames(
            "cgc",
            f"Gray code bits 0..{m - 1} along {axis} (gray:{axis}:bit=0-{m - 1}) and a {steps or 'N'}-step phase "
            f"shift along {axis} with period {W}/{1 << (m - 1)} = {size / (1 << (m - 1)):g} px "
            f"(phase:{axis}:period={size / (1 << (m - 1)):g}; in general: n Gray code bits and period "
            f"{W}/2^(n-1); cgc6 = 3 bits + {W}/4, cgc7 = 4 bits + {W}/8)",
            scan,
        )
    m, pset = choice
    gf = gray_frames(scan, axis, m)
    u, extra = decode_gray_phase(gf, pset, min_amplitude, min_bit_contrast)
    used = gf.used + pset.names
    extra.update(bits=m, periods=[pset.period])
    return finalize_positions(u, size), used, extra


def _gt(scan, axis, period: float = 40.0, steps: int | None = 4, bits: int | None = None,
        min_amplitude=DEFAULT_MIN_AMPLITUDE, min_bit_contrast=0.0):
    size = axis_size(scan, axis)
    gf = gray_frames(scan, axis, bits)
    pset = _find_set(phase_sets(scan, axis), period, steps)
    if gf is None or pset is None:
        nb = bits or 7
        raise MissingFrames(
            "gt", f"Gray code bits 0..{nb - 1} along {axis} with inverses (gray:{axis}:bit=0-{nb - 1}, slwarp names "
            f"gc_{axis}_b0..gc_{axis}_b{nb - 1} and _inv) and a {steps or 'N'}-step phase shift along {axis} with "
            f"period {period:g} px (phase:{axis}:period={period:g}); the set 'gt'", scan)
    u, extra = decode_gray_phase(gf, pset, min_amplitude, min_bit_contrast)
    used = gf.used + pset.names
    extra.update(bits=gf.bits, periods=[pset.period])
    return finalize_positions(u, size), used, extra


def _hpmp(scan, axis, short_period: float = 80.0, steps: int | None = 3, min_amplitude=DEFAULT_MIN_AMPLITUDE):
    size = axis_size(scan, axis)
    sets = phase_sets(scan, axis)
    coarse = [s for s in sets if s.period >= size - 1e-6]
    if steps is not None and any(s.steps == steps for s in coarse):
        coarse = [s for s in coarse if s.steps == steps]
    coarse = min(coarse, key=lambda s: (s.period, -s.steps)) if coarse else None
    fine = _find_set(sets, short_period, steps)
    if coarse is None or fine is None:
        n = steps or "N"
        raise MissingFrames(
            "hpmp", f"a {n}-step phase shift along {axis} with one period across the axis "
            f"(phase:{axis}:period={size}) and a {n}-step one with the short period "
            f"(phase:{axis}:period={short_period:g}); the set 'hpmp6'", scan)
    phi_c, _, mod_c = wrapped_phase(coarse.images, coarse.shifts)
    phi_f, _, mod_f = wrapped_phase(fine.images, fine.shifts)
    u_c = coarse_position(phi_c, coarse.period)
    u = unwrap_with_reference(wrapped_position(phi_f, fine.period), u_c, fine.period)
    valid = (mod_c >= min_amplitude) & (mod_f >= min_amplitude)
    u = finalize_positions(np.where(valid, u, np.nan), size)
    return u, coarse.names + fine.names, {"modulation": np.minimum(mod_c, mod_f), "coarse": u_c,
                                          "periods": [coarse.period, fine.period]}


def _npmp(scan, axis, periods=(48, 70), steps: int | None = 3, min_amplitude=DEFAULT_MIN_AMPLITUDE):
    size = axis_size(scan, axis)
    sets = phase_sets(scan, axis)
    p1, p2 = (float(p) for p in periods)
    s1, s2 = _find_set(sets, p1, steps), _find_set(sets, p2, steps)
    if s1 is None or s2 is None:
        n = steps or "N"
        raise MissingFrames(
            "npmp", f"two {n}-step phase shifts along {axis} with co-prime periods (phase:{axis}:period={p1:g} "
            f"and phase:{axis}:period={p2:g}); the set 'npmp6'", scan)
    phi1, _, m1 = wrapped_phase(s1.images, s1.shifts)
    phi2, _, m2 = wrapped_phase(s2.images, s2.shifts)
    table = NumberTheoreticTable(p1, p2, size)
    u, disagreement = unwrap_number_theoretic(wrapped_position(phi1, p1), wrapped_position(phi2, p2), p1, p2, size, table)
    valid = (m1 >= min_amplitude) & (m2 >= min_amplitude)
    u = finalize_positions(np.where(valid, u, np.nan), size)
    return u, s1.names + s2.names, {"modulation": np.minimum(m1, m2), "disagreement": disagreement,
                                    "periods": [p1, p2]}


def _axis_method(fn):
    """Adapt a one-axis method (returning u, frames, extra) to the (col, row, frames, extra) form.

    axis=None (the default) decodes the axis that carries depth on this rig (`choose_plane_axis`) when the
    scan has that method's frames for it, else the other axis; the error, when neither has them, is the one
    of the depth-carrying axis."""

    def run(scan, axis=None, **kw):
        if axis is None:
            first = choose_plane_axis(scan.projector)
            try:
                return run(scan, first, **kw)
            except MissingFrames as e:
                try:
                    return run(scan, "row" if first == "col" else "col", **kw)
                except MissingFrames:
                    raise e from None
        if axis not in ("col", "row"):
            raise ValueError(f"axis must be 'col' or 'row', got {axis!r}")
        u, used, extra = fn(scan, axis=axis, **kw)
        extra["axis"] = axis
        return (u, None, used, extra) if axis == "col" else (None, u, used, extra)

    return run


@dataclass
class Method:
    """A decoding method: `fn(scan, **params) -> (col, row, frames used, extra)`, a one-line summary,
    and the pattern sets (`slwarp.scans.patterns.named_set`) that provide its frames."""

    name: str
    fn: object
    summary: str
    pattern_sets: str


METHODS: dict[str, Method] = {
    m.name: m
    for m in [
        Method("gc", lambda scan, **kw: _gc(scan, False, **kw),
               "Gray code, centre of the decoded stripe (column and row codes, whichever the scan has)",
               "grayN, grayNinv (+whiteblack), grayrowN[inv]"),
        Method("gc-interp", lambda scan, **kw: _gc(scan, True, **kw),
               "Gray code with linear interpolation between sub-pixel stripe transitions (the paper's GC)",
               "grayN, grayNinv (+whiteblack), grayrowN[inv]"),
        Method("ps", _axis_method(_ps), "N-step phase shift with one period across the projector", "psN"),
        Method("cgc", _axis_method(_cgc),
               "complementary Gray code: n Gray code bits + 3-step phase shift with period W/2^(n-1)", "cgc6, cgc7"),
        Method("hpmp", _axis_method(_hpmp),
               "hierarchical PMP: 3-step at period W unwraps 3-step at 80 px", "hpmp6"),
        Method("npmp", _axis_method(_npmp),
               "number-theoretic PMP: 3-step at 48 and 70 px, unwrapped by lookup", "npmp6"),
        Method("gt", _axis_method(_gt),
               "ground-truth pipeline: 7-bit Gray code with inverses + 4-step phase shift, period 40 px", "gt"),
    ]
}


def decode(scan, method: str, frames=None, **params) -> Decoding:
    """Decode a scan with one of `METHODS` (after selecting `frames`, see `Scan.select`).

    params go to the method: min_amplitude, min_bit_contrast (Gray code), axis ('col'/'row' or None: the
    depth-carrying axis the scan has frames for; phase methods),
    bits (gc, gc-interp, cgc, gt), short_period (hpmp), periods (npmp), period and steps (gt), fallback
    (gc-interp: 'extrapolate', 'center' or 'nan'). Raises `MissingFrames` when the scan lacks the method's frames.
    """
    if method not in METHODS:
        raise ValueError(f"unknown decoding method {method!r}; methods: {', '.join(METHODS)}")
    if frames is not None:
        scan = scan.select(frames)
    t0 = time.perf_counter()
    col, row, used, extra = METHODS[method].fn(scan, **params)
    valid = np.ones((scan.camera.height, scan.camera.width), bool)
    for c in (col, row):
        if c is not None:
            valid &= np.isfinite(c)
    extra["decode_s"] = time.perf_counter() - t0
    return Decoding(col, row, valid, method, list(dict.fromkeys(used)), extra)


def reconstruct_depth(scan, method: str, frames=None, triangulation: str = "auto", depth_range="scan",
                      **params) -> tuple[np.ndarray, np.ndarray, Decoding]:
    """Decode and triangulate: (depth [H, W] float64 mm NaN invalid, points [H, W, 3] mm camera frame, Decoding).

    triangulation: 'auto' (from the rig and the coordinates decoded: `triangulate.choose_triangulation`),
    'col', 'row', 'both' or 'midpoint'.
    depth_range: 'scan' (the scan's declared working range, when it has one), None, or (near, far) mm;
    points outside it are NaN.
    """
    dec = decode(scan, method, frames, **params)
    dr = scan.depth_range if isinstance(depth_range, str) and depth_range == "scan" else depth_range
    t0 = time.perf_counter()
    depth, points, info = triangulate(scan.camera, scan.projector, dec.col, dec.row, triangulation, dr)
    dec.extra["triangulation"] = info["mode"]
    dec.extra["baseline_alignment"] = info["alignment"]
    if "gap" in info:
        dec.extra["ray_gap"] = info["gap"]
    dec.extra["triangulate_s"] = time.perf_counter() - t0
    return depth, points, dec
