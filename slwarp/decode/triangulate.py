"""Triangulation of camera pixels with decoded projector coordinates -> depth maps and point clouds.

- Plane method: the camera ray of each pixel meets the surface of projector rays through its decoded
  projector column (or row). Without projector distortion that surface is the plane x_p / z_p = x_n through
  the projector centre (x_n: the column's normalised coordinate). With distortion, the undistorted x_n of a
  column depends slightly on the row, so the surface is curved. One could iterate: intersect with the
  plane of (u_p, v_guess), project the 3-D point into the projector to update v_guess, repeat. We start
  like that (v_guess = principal row) and then solve the same fixed point by Newton's method on the ray
  parameter, which needs projections only (no undistortion per step) and converges quadratically.
- Midpoint method: when both projector coordinates are decoded, the point halfway between the closest
  points of the camera ray and the projector ray.

The camera's distortion is handled by `Camera.pixel_to_ray`. All arithmetic is float64 numpy.
Conventions: mm, camera frame (OpenCV axes), X_p = R X_c + T; outputs NaN where invalid.
"""
from __future__ import annotations

import numpy as np

from ..scans.scanner import Camera, Projector

__all__ = ["choose_plane_axis", "camera_rays", "triangulate_plane", "triangulate_midpoint", "triangulate"]

TRIANGULATION_MODES = ("auto", "col", "row", "midpoint")


def choose_plane_axis(projector: Projector) -> str:
    """'col' when the baseline (the camera centre in the projector frame, T) runs mostly along the
    projector's x axis (|T_x| >= |T_y|), else 'row': the coordinate that changes with depth the most."""
    return "col" if abs(projector.T[0]) >= abs(projector.T[1]) else "row"


def camera_rays(camera: Camera, uv: np.ndarray | None = None) -> np.ndarray:
    """Unit ray directions [..., 3] (camera frame) of pixels uv [..., 2] (default: every pixel, [H, W, 3])."""
    uv = camera.pixel_grid() if uv is None else np.asarray(uv, np.float64)
    return camera.pixel_to_ray(uv)


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
    coord = np.asarray(coord, np.float64)
    H, W = coord.shape
    out = np.full((H, W, 3), np.nan)
    sel = np.isfinite(coord)
    if not sel.any():
        return out
    d = (camera_rays(camera) if rays is None else rays)[sel]
    c = coord[sel]
    a = 0 if axis == "col" else 1  # the decoded coordinate
    uv = np.empty((c.size, 2))
    uv[:, a], uv[:, 1 - a] = c, (projector.cy if axis == "col" else projector.cx)
    t = _plane_intersection(d, projector, projector.pixel_to_normalized(uv)[:, a], axis)
    Rd = d @ projector.R.T  # ray directions in the projector frame
    T = projector.T
    f = projector.fx if a == 0 else projector.fy
    pc = projector.cx if a == 0 else projector.cy
    r2_max = projector.max_normalized_r2
    with np.errstate(divide="ignore", invalid="ignore"):
        for _ in range(max(0, iterations) + 1):
            Xp = t[:, None] * Rd + T
            Z = Xp[:, 2]
            x, y = Xp[:, 0] / Z, Xp[:, 1] / Z
            dx = (Rd[:, 0] * Z - Xp[:, 0] * Rd[:, 2]) / (Z * Z)  # d x / d t
            dy = (Rd[:, 1] * Z - Xp[:, 1] * Rd[:, 2]) / (Z * Z)
            xd, yd, jxx, jxy, jyy = _distort_with_jacobian(x, y, projector.dist)
            if a == 0:
                val, der = f * xd + pc, f * (jxx * dx + jxy * dy)
            else:
                val, der = f * yd + pc, f * (jxy * dx + jyy * dy)
            # outside the trusted radius the distortion polynomial can fold back: no solution there
            trusted = (Z > 0) & (x * x + y * y <= r2_max)
            resid = np.where(trusted, val - c, np.nan)
            if _ == iterations:
                break
            t = t - resid / der
            t = np.where(t > 0, t, np.nan)
    X = d * t[:, None]
    X[~(np.abs(resid) <= tol_px)] = np.nan
    out[sel] = X
    return out


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

    mode: 'col' or 'row' (plane method), 'midpoint' (needs both), or 'auto': the plane of the coordinate
    along the baseline (`choose_plane_axis`), or the other one when only that was decoded.
    depth_range: (near, far) mm or None; points outside it become NaN (a wrongly decoded coordinate
    triangulates far from the working volume).
    Returns (depth, points, info) with info['mode'] the method used (and 'gap' [H, W] for the midpoint).
    """
    if mode not in TRIANGULATION_MODES:
        raise ValueError(f"triangulation must be one of {', '.join(TRIANGULATION_MODES)}, got {mode!r}")
    if col is None and row is None:
        raise ValueError("triangulation needs a decoded projector column or row")
    info: dict = {}
    if mode == "auto":
        mode = choose_plane_axis(projector)
        if mode == "col" and col is None:
            mode = "row"
        elif mode == "row" and row is None:
            mode = "col"
    rays = camera_rays(camera)
    if mode == "midpoint":
        if col is None or row is None:
            raise ValueError("midpoint triangulation needs both projector coordinates (column and row codes)")
        pts, info["gap"] = triangulate_midpoint(camera, projector, col, row, rays)
    else:
        coord = col if mode == "col" else row
        if coord is None:
            raise ValueError(f"triangulation with projector {mode}s needs decoded projector {mode}s")
        pts = triangulate_plane(camera, projector, coord, mode, rays=rays)
    info["mode"] = mode
    depth = pts[..., 2].copy()
    if depth_range is not None:
        near, far = depth_range
        with np.errstate(invalid="ignore"):
            out = ~((depth >= near) & (depth <= far))
        depth[out] = np.nan
        pts[out] = np.nan
    return depth, pts, info
