"""Triangulation of camera pixels with decoded projector coordinates -> depth maps and point clouds.

- Plane method: the camera ray of each pixel meets the surface of projector rays through its decoded
  projector column (or row). Without projector distortion that surface is the plane x_p / z_p = x_n through
  the projector centre (x_n: the column's normalised coordinate). With distortion, the undistorted x_n of a
  column depends slightly on the row, so the surface is curved. One could iterate: intersect with the
  plane of (u_p, v_guess), project the 3-D point into the projector to update v_guess, repeat. We start
  like that (v_guess = principal row) and then solve the same fixed point by Newton's method on the ray
  parameter, which needs projections only (no undistortion per step) and converges quadratically.
- Both coordinates ('both'): the point on the camera ray whose projection best matches the decoded column
  and row, least squares in projector px (Gauss-Newton on the same ray parameter). Each coordinate counts
  by how fast it changes along the ray, so on an oblique baseline both codes carry depth and their errors
  average, and a coordinate that barely changes along the ray barely counts.
- Midpoint method: when both projector coordinates are decoded, the point halfway between the closest
  points of the camera ray and the projector ray.

Which surface carries depth is a property of the rig: the projector coordinate that changes along the
baseline (`baseline_alignment`). `triangulate(mode='auto')` picks the plane of the best-aligned coordinate,
or both coordinates when the baseline is oblique (22.5 to 67.5 deg from the projector's axes) and both were
decoded.

The camera's distortion is handled by `Camera.pixel_to_ray`. All arithmetic is float64 numpy.
Conventions: mm, camera frame (OpenCV axes), X_p = R X_c + T; outputs NaN where invalid.
"""
from __future__ import annotations

import numpy as np

from ..scans.scanner import Camera, Projector, camera_rays

__all__ = ["baseline_alignment", "choose_plane_axis", "choose_triangulation", "triangulate_plane",
           "triangulate_rays", "triangulate_midpoint", "triangulate"]

TRIANGULATION_MODES = ("auto", "col", "row", "both", "midpoint")
# on a baseline this far (deg) from both projector axes, both coordinates carry depth and 'auto' uses both
OBLIQUE_DEG = 22.5


def baseline_alignment(projector: Projector) -> dict[str, float]:
    """How much of the baseline each projector coordinate sees: {'col': |cos a|, 'row': |sin a|}, where a is
    the angle of the baseline in the projector's image plane (the camera centre in the projector frame is T;
    its (x, y) part runs along the projector's columns axis x and rows axis y). The coordinate with the
    larger share changes the most with depth; one with a share near 0 carries (almost) no depth."""
    tx, ty = abs(float(projector.T[0])), abs(float(projector.T[1]))
    n = np.hypot(tx, ty)
    if n == 0:
        return {"col": 0.0, "row": 0.0}  # camera and projector on one optical axis: no stereo baseline
    return {"col": tx / n, "row": ty / n}


def choose_plane_axis(projector: Projector) -> str:
    """'col' when the baseline runs mostly along the projector's x axis (|T_x| >= |T_y|), else 'row': the
    coordinate that changes with depth the most."""
    a = baseline_alignment(projector)
    return "col" if a["col"] >= a["row"] else "row"


def choose_triangulation(projector: Projector, has_col: bool, has_row: bool) -> str:
    """The triangulation for the codes at hand: 'both' on an oblique baseline (more than OBLIQUE_DEG from
    either projector axis) when both coordinates are decoded, else the plane of the best-aligned decoded
    coordinate ('col' or 'row'); the other one only when it alone was decoded."""
    if not (has_col or has_row):
        raise ValueError("triangulation needs a decoded projector column or row")
    a = baseline_alignment(projector)
    oblique = min(a["col"], a["row"]) >= np.sin(np.radians(OBLIQUE_DEG))
    if has_col and has_row and oblique:
        return "both"
    best = choose_plane_axis(projector)
    if best == "col":
        return "col" if has_col else "row"
    return "row" if has_row else "col"


def _plane_intersection(d: np.ndarray, projector: Projector, n_coord: np.ndarray, axis: str) -> np.ndarray:
    """Ray parameter t of camera rays d [M, 3] (from the origin) with the projector-frame planes
    X_p[i] = n_coord * Z_p (i = 0 for columns, 1 for rows). NaN where parallel or behind the camera."""
    i = 0 if axis == "col" else 1
    Rd = d @ projector.R.T  # ray directions in the projector frame
    T = projector.T
    num = -(T[i] - n_coord * T[2])
    den = Rd[:, i] - n_coord * Rd[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = num / den
    return np.where((np.abs(den) > 1e-12) & (t > 0), t, np.nan)


def _distort_with_jacobian(x, y, dist):
    """OpenCV's radial-tangential model (as `slwarp.scans.scanner.distort_normalized`) and its Jacobian:
    (xd, yd, dxd/dx, dxd/dy = dyd/dx, dyd/dy)."""
    k1, k2, p1, p2, k3 = (float(c) for c in dist)
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d radial / d r2
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    jxx = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
    jxy = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
    jyy = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
    return xd, yd, jxx, jxy, jyy


def _solve_along_rays(camera: Camera, projector: Projector, col, row, iterations: int, rays, tol_px: float):
    """Points [H, W, 3] on the camera rays whose projections best match the decoded coordinates given
    (col and/or row [H, W], NaN invalid), least squares in projector px, and the remaining residual [H, W]
    (px, RMS over the coordinates used). Start: the plane of the better-aligned given coordinate through its
    undistorted ray (at the principal row or column when only one is given); then Gauss-Newton on the ray
    parameter t with the analytic derivative of the projection, distortion included (Newton's method when
    one coordinate is given). A point whose remaining correction exceeds `tol_px` in projector px is NaN
    (no solution on this ray: e.g. beyond the trusted radius of the distortion polynomial)."""
    given = {a: np.asarray(c, np.float64) for a, c in (("col", col), ("row", row)) if c is not None}
    shape = next(iter(given.values())).shape
    H, W = shape
    out = np.full((H, W, 3), np.nan)
    residual = np.full((H, W), np.nan)
    sel = np.ones(shape, bool)
    for c in given.values():
        sel &= np.isfinite(c)
    if not sel.any():
        return out, residual
    d = (camera_rays(camera) if rays is None else rays)[sel]
    c_col = given["col"][sel] if "col" in given else None
    c_row = given["row"][sel] if "row" in given else None
    start_axis = choose_plane_axis(projector) if len(given) == 2 else next(iter(given))
    uv = np.empty((d.shape[0], 2))
    uv[:, 0] = c_col if c_col is not None else projector.cx
    uv[:, 1] = c_row if c_row is not None else projector.cy
    a0 = 0 if start_axis == "col" else 1
    t = _plane_intersection(d, projector, projector.pixel_to_normalized(uv)[:, a0], start_axis)
    Rd = d @ projector.R.T  # ray directions in the projector frame
    T = projector.T
    r2_max = projector.max_normalized_r2
    with np.errstate(divide="ignore", invalid="ignore"):
        for it in range(max(0, iterations) + 1):
            Xp = t[:, None] * Rd + T
            Z = Xp[:, 2]
            x, y = Xp[:, 0] / Z, Xp[:, 1] / Z
            dx = (Rd[:, 0] * Z - Xp[:, 0] * Rd[:, 2]) / (Z * Z)  # d x / d t
            dy = (Rd[:, 1] * Z - Xp[:, 1] * Rd[:, 2]) / (Z * Z)
            xd, yd, jxx, jxy, jyy = _distort_with_jacobian(x, y, projector.dist)
            # outside the trusted radius the distortion polynomial can fold back: no solution there
            trusted = (Z > 0) & (x * x + y * y <= r2_max)
            num = np.zeros_like(t)  # sum of residual * derivative
            den = np.zeros_like(t)  # sum of derivative^2
            sq = np.zeros_like(t)
            if c_col is not None:
                r, j = projector.fx * xd + projector.cx - c_col, projector.fx * (jxx * dx + jxy * dy)
                num, den, sq = num + r * j, den + j * j, sq + r * r
            if c_row is not None:
                r, j = projector.fy * yd + projector.cy - c_row, projector.fy * (jxy * dx + jyy * dy)
                num, den, sq = num + r * j, den + j * j, sq + r * r
            step = np.where(trusted, num / den, np.nan)
            # converged everywhere (the start is within a few px; Newton halves the digits' error each step)
            if it == iterations or not (np.abs(step) * np.sqrt(den) > 1e-6 * tol_px).any():
                break
            t = t - step
            t = np.where(t > 0, t, np.nan)
    X = d * t[:, None]
    # |num| / sqrt(den): the residual's component that moving along the ray could still remove (px)
    X[~(np.abs(step) * np.sqrt(den) <= tol_px)] = np.nan
    out[sel] = X
    residual[sel] = np.where(np.isfinite(X[:, 2]), np.sqrt(sq / len(given)), np.nan)
    return out, residual


def triangulate_plane(camera: Camera, projector: Projector, coord: np.ndarray, axis: str = "col",
                      iterations: int = 6, rays: np.ndarray | None = None, tol_px: float = 1e-3) -> np.ndarray:
    """Points [H, W, 3] (mm, camera frame; NaN invalid) from a decoded projector column (axis='col') or
    row ('row') per camera pixel, coord [H, W] in continuous projector px (distorted, as decoded; NaN
    invalid). `rays` [H, W, 3]: precomputed `camera_rays(camera)`.

    Start: the plane of the coordinate's undistorted ray at the principal row (column); then Newton's
    method on the ray parameter t for projector_coord(t d) = coord, with the analytic derivative of the
    projection (distortion included). This is the intersection with the curved surface of projector rays
    of that column, the limit of the plane iteration described in the module docstring, at a fraction of
    its cost. A point that does not reproject onto its coordinate within `tol_px` is NaN.
    """
    if axis not in ("col", "row"):
        raise ValueError(f"axis must be 'col' or 'row', got {axis!r}")
    col, row = (coord, None) if axis == "col" else (None, coord)
    return _solve_along_rays(camera, projector, col, row, iterations, rays, tol_px)[0]


def triangulate_rays(camera: Camera, projector: Projector, col: np.ndarray, row: np.ndarray, iterations: int = 8,
                     rays: np.ndarray | None = None, tol_px: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """Points [H, W, 3] on the camera rays that best match both decoded coordinates col, row [H, W] (least
    squares in projector px; NaN where either is NaN) and the remaining residual [H, W] (px RMS over the two
    coordinates: large where the decodings disagree)."""
    return _solve_along_rays(camera, projector, col, row, iterations, rays, tol_px)


def triangulate_midpoint(camera: Camera, projector: Projector, col: np.ndarray, row: np.ndarray,
                         rays: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Ray-ray midpoint from both projector coordinates (distortion of both lenses handled by their ray
    functions). col, row [H, W] (NaN invalid) -> (points [H, W, 3] NaN invalid, gap [H, W]: the distance
    between the two rays at their closest points, mm; a large gap means inconsistent decoding)."""
    col, row = np.asarray(col, np.float64), np.asarray(row, np.float64)
    H, W = col.shape
    pts = np.full((H, W, 3), np.nan)
    gap = np.full((H, W), np.nan)
    sel = np.isfinite(col) & np.isfinite(row)
    if not sel.any():
        return pts, gap
    d1 = (camera_rays(camera) if rays is None else rays)[sel]
    d2 = projector.pixel_to_ray_in_camera(np.stack([col[sel], row[sel]], -1))
    c2 = projector.center
    # closest points o1 + s d1 and c2 + t d2 (o1 = 0, unit directions)
    w0 = -c2
    b = (d1 * d2).sum(-1)
    dd = (d1 * w0).sum(-1)
    e = (d2 * w0).sum(-1)
    den = 1.0 - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (b * e - dd) / den
        t = (e - b * dd) / den
    p1 = d1 * s[:, None]
    p2 = c2 + d2 * t[:, None]
    ok = (den > 1e-12) & (s > 0) & (t > 0)
    mid = 0.5 * (p1 + p2)
    mid[~ok] = np.nan
    pts[sel] = mid
    gap[sel] = np.where(ok, np.linalg.norm(p1 - p2, axis=-1), np.nan)
    return pts, gap


def triangulate(camera: Camera, projector: Projector, col: np.ndarray | None = None, row: np.ndarray | None = None,
                mode: str = "auto", depth_range=None) -> tuple[np.ndarray, np.ndarray, dict]:
    """Depth [H, W] (z, mm, NaN invalid) and points [H, W, 3] from decoded projector coordinates.

    mode: 'col' or 'row' (plane method), 'both' (least squares on both coordinates along the camera ray),
    'midpoint' (ray-ray midpoint; needs both), or 'auto' (`choose_triangulation`: from the rig's baseline
    and the coordinates decoded).
    depth_range: (near, far) mm or None; points outside it become NaN (a wrongly decoded coordinate
    triangulates far from the working volume).
    Returns (depth, points, info): info['mode'] the method used, info['alignment'] the share of the baseline
    that the coordinate(s) used see (1: along it; near 0: the surface nearly contains the camera rays and
    depth is ill-conditioned), 'gap' [H, W] for the midpoint, 'residual' [H, W] for 'both'.
    """
    if mode not in TRIANGULATION_MODES:
        raise ValueError(f"triangulation must be one of {', '.join(TRIANGULATION_MODES)}, got {mode!r}")
    if col is None and row is None:
        raise ValueError("triangulation needs a decoded projector column or row")
    info: dict = {}
    if mode == "auto":
        mode = choose_triangulation(projector, col is not None, row is not None)
    rays = camera_rays(camera)
    if mode in ("midpoint", "both"):
        if col is None or row is None:
            raise ValueError(f"{mode} triangulation needs both projector coordinates (column and row codes)")
        if mode == "midpoint":
            pts, info["gap"] = triangulate_midpoint(camera, projector, col, row, rays)
        else:
            pts, info["residual"] = triangulate_rays(camera, projector, col, row, rays=rays)
    else:
        coord = col if mode == "col" else row
        if coord is None:
            raise ValueError(f"triangulation with projector {mode}s needs decoded projector {mode}s")
        pts = triangulate_plane(camera, projector, coord, mode, rays=rays)
    info["mode"] = mode
    a = baseline_alignment(projector)
    info["alignment"] = a[mode] if mode in a else 1.0 if a["col"] + a["row"] > 0 else 0.0
    depth = pts[..., 2].copy()
    if depth_range is not None:
        near, far = depth_range
        with np.errstate(invalid="ignore"):
            out = ~((depth >= near) & (depth <= far))
        depth[out] = np.nan
        pts[out] = np.nan
    return depth, pts, info
