"""Camera and projector models: pinhole intrinsics with OpenCV lens distortion.

Conventions (binding across slwarp):
- millimetres; camera frame x right, y down, z forward (OpenCV);
- pixel (u, v) = (column, row), the centre of pixel (0, 0) at continuous coordinate (0, 0);
- distortion is OpenCV's (k1, k2, p1, p2, k3) model applied to normalised coordinates;
- a camera-frame point X_c maps to the projector frame as X_p = R X_c + T.

Every geometric function accepts numpy arrays or torch tensors (any device, any float dtype) with the
coordinate axis last, and returns the same kind of array. `camera_rays(camera)` is the camera's grid of unit pixel
rays (numpy), cached per camera: the decoders' triangulation, the depth search, the pattern model and the extraction
share it.
"""
from __future__ import annotations

import os
import sys
import threading
from dataclasses import dataclass, field
from functools import cached_property
from typing import NamedTuple

import numpy as np


class CalibrationError(ValueError):
    """A calibration that cannot describe a real device (non-finite, singular, not a rotation)."""


def _torch():
    """torch, once the process has imported it (a tensor cannot exist before). Geometry does not import torch itself,
    so that a scan can load while the process imports torch (scans.prefetch)."""
    return sys.modules.get("torch")


def _is_torch(x) -> bool:
    torch = _torch()
    return torch is not None and isinstance(x, torch.Tensor)


def bounded_cache(store: dict, key, build, keep: int = 4):
    """store[key], built by build() the first time; a store that holds `keep` entries is emptied first. For the
    caches of the last few rigs (ray grids, device copies) and of small constants, whose values are used read-only."""
    value = store.get(key)
    if value is None:
        if len(store) >= keep:
            store.clear()
        value = store[key] = build()
    return value


_SMALL_CONSTANTS: dict = {}


def const_like(value, like):
    """`value` (numpy, list) as an array of the same kind, dtype and device as `like`.

    Small torch constants (rig parameters, bounds: up to 16 numbers) are made once per dtype and device:
    building one each call copies host memory to the GPU and synchronises, which a CUDA graph capture forbids."""
    if not _is_torch(like):
        return np.asarray(value, dtype=np.result_type(like.dtype, np.float32))
    arr = np.asarray(value)
    if arr.size > 16:
        return _torch().as_tensor(arr, dtype=like.dtype, device=like.device)
    key = (arr.shape, arr.astype(np.float64).tobytes(), like.dtype, like.device)
    return bounded_cache(_SMALL_CONSTANTS, key, lambda: _torch().as_tensor(arr, dtype=like.dtype, device=like.device),
                         keep=257)


def _rotate(x, M):
    """x [..., 3] -> M x [..., 3]. For torch tensors written out elementwise, since a matmul would run in
    TF32 (10-bit mantissa: ~1 mm at 1 m) whenever training has switched TF32 on."""
    if _is_torch(x):
        return (x[..., None, :] * const_like(M, x)).sum(-1)
    return x @ np.asarray(M).T


def _stack(parts, like):
    return _torch().stack(parts, dim=-1) if _is_torch(like) else np.stack(parts, axis=-1)


def _as_float(x):
    if _is_torch(x):
        return x if x.is_floating_point() else x.float()
    x = np.asarray(x)
    return x if np.issubdtype(x.dtype, np.floating) else x.astype(np.float64)


# ----------------------------------------------------------------------------------------------
# OpenCV distortion on normalised coordinates


def distort_normalized(x, y, dist):
    """OpenCV's radial-tangential model. x, y: undistorted normalised coords -> distorted ones."""
    k1, k2, p1, p2, k3 = (float(c) for c in dist)
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return xd, yd


def undistort_normalized(xd, yd, dist, iterations: int = 12):
    """Inverse of `distort_normalized` by Newton's method with the analytic 2x2 Jacobian.

    Converges to float precision within a few steps for any distortion that is invertible over the
    image (the usual case); 12 steps leave ample margin.
    """
    k1, k2, p1, p2, k3 = (float(c) for c in dist)
    if k1 == k2 == p1 == p2 == k3 == 0.0:
        return xd, yd
    x, y = xd, yd
    for _ in range(iterations):
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d radial / d r2
        fx = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) - xd
        fy = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y - yd
        jxx = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
        jxy = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
        jyy = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
        det = jxx * jyy - jxy * jxy
        dx = (jyy * fx - jxy * fy) / det
        dy = (jxx * fy - jxy * fx) / det
        x = x - dx
        y = y - dy
        if not _is_torch(dx) and np.max(np.abs(dx), initial=0.0) < 1e-14 and np.max(np.abs(dy), initial=0.0) < 1e-14:
            break  # converged (numpy only: a check on a GPU tensor would synchronise)
    return x, y


# ----------------------------------------------------------------------------------------------


def _check_intrinsics(K, dist, width, height, what: str):
    if int(width) <= 0 or int(height) <= 0:
        raise CalibrationError(f"{what}: image size must be positive, got {width}x{height}")
    if K.shape != (3, 3):
        raise CalibrationError(f"{what}: K must be 3x3, got shape {K.shape}")
    if not np.all(np.isfinite(K)):
        raise CalibrationError(f"{what}: K has non-finite entries:\n{K}")
    if not np.all(np.isfinite(dist)):
        raise CalibrationError(f"{what}: distortion has non-finite entries: {dist}")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or abs(np.linalg.det(K)) < 1e-9 or not np.allclose(K[2], [0, 0, 1]):
        raise CalibrationError(
            f"{what}: K is singular or not an intrinsic matrix (need fx, fy > 0 and last row 0 0 1):\n{K}"
        )


def _as_dist(dist) -> np.ndarray:
    d = np.zeros(5, dtype=np.float64)
    if dist is not None:
        src = np.asarray(dist, dtype=np.float64).ravel()
        if src.size not in (0, 4, 5, 8, 12, 14):
            raise CalibrationError(f"distortion needs 4 or 5 coefficients (k1 k2 p1 p2 [k3]), got {src.size}")
        if src.size > 5 and np.any(src[5:] != 0):
            raise CalibrationError("only OpenCV's (k1, k2, p1, p2, k3) distortion model is supported")
        d[: min(5, src.size)] = src[:5]
    return d


@dataclass
class Camera:
    """Pinhole camera with OpenCV distortion.

    width, height: image size in pixels; K: 3x3 intrinsics (fx, fy, cx, cy in pixels, no skew);
    dist: (k1, k2, p1, p2, k3).
    """

    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))

    def __post_init__(self):
        self.width, self.height = int(self.width), int(self.height)
        self.K = np.asarray(self.K, dtype=np.float64)
        if self.K.size == 9:
            self.K = self.K.reshape(3, 3)
        self.dist = _as_dist(self.dist)
        _check_intrinsics(self.K, self.dist, self.width, self.height, type(self).__name__)

    @property
    def cache_key(self) -> tuple:
        """What a cache of per-camera values (ray grids) is keyed on: the image size and the intrinsics."""
        return (self.width, self.height, self.K.tobytes(), self.dist.tobytes())

    # --- intrinsics -------------------------------------------------------------------------
    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return self.width, self.height

    # --- pixel <-> normalised ---------------------------------------------------------------
    def pixel_to_normalized(self, uv):
        """uv [..., 2] pixels -> undistorted normalised coordinates [..., 2] (x/z, y/z)."""
        uv = _as_float(uv)
        xd = (uv[..., 0] - self.cx) / self.fx
        yd = (uv[..., 1] - self.cy) / self.fy
        x, y = undistort_normalized(xd, yd, self.dist)
        return _stack([x, y], uv)

    def normalized_to_pixel(self, xy):
        """Undistorted normalised coordinates [..., 2] -> distorted pixels [..., 2]."""
        xy = _as_float(xy)
        xd, yd = distort_normalized(xy[..., 0], xy[..., 1], self.dist)
        return _stack([xd * self.fx + self.cx, yd * self.fy + self.cy], xy)

    def pixel_to_ray(self, uv):
        """uv [..., 2] pixels -> unit ray directions [..., 3] in this device's frame."""
        xy = self.pixel_to_normalized(uv)
        one = xy[..., 0] * 0 + 1
        d = _stack([xy[..., 0], xy[..., 1], one], xy)
        norm = _torch().linalg.norm(d, dim=-1, keepdim=True) if _is_torch(d) else np.linalg.norm(d, axis=-1, keepdims=True)
        return d / norm

    @cached_property
    def max_normalized_r2(self) -> float:
        """Squared normalised radius up to which the distortion polynomial is trusted.

        OpenCV's polynomial folds back for large radii when k2/k3 are strong (a point far outside the
        field of view can land inside the image). We trust it up to 1.5x the image's own extent in r^2,
        and never beyond the first radius where the radial mapping stops increasing.
        """
        w, h = self.width, self.height
        t = np.linspace(0.0, 1.0, 65)
        border = np.concatenate([
            np.stack([t * (w - 1), np.zeros_like(t)], -1), np.stack([t * (w - 1), np.full_like(t, h - 1)], -1),
            np.stack([np.zeros_like(t), t * (h - 1)], -1), np.stack([np.full_like(t, w - 1), t * (h - 1)], -1),
        ])
        xy = self.pixel_to_normalized(border)
        r2_image = float(np.max((xy ** 2).sum(-1)))
        k1, k2, _, _, k3 = self.dist
        r2 = np.linspace(0.0, 4.0 * r2_image + 1e-9, 4001)
        slope = 1 + 3 * k1 * r2 + 5 * k2 * r2**2 + 7 * k3 * r2**3  # d(r * radial(r)) / dr
        folds = r2[slope <= 0.05]
        limit = 1.5 * r2_image
        return float(min(limit, 0.95 * folds[0]) if folds.size else limit)

    def project(self, X):
        """Points [..., 3] in this device's frame -> distorted pixels [..., 2].

        Points at or behind the optical centre (z <= 0) or far outside the field of view (beyond
        `max_normalized_r2`, where the distortion polynomial is not trusted) give NaN.
        """
        X = _as_float(X)
        z = X[..., 2]
        if _is_torch(z):
            z = _torch().where(z > 0, z, _torch().full_like(z, float("nan")))
        else:
            z = np.where(z > 0, z, np.nan)
        x, y = X[..., 0] / z, X[..., 1] / z
        far = (x * x + y * y) > self.max_normalized_r2
        if _is_torch(far):
            x = _torch().where(far, _torch().full_like(x, float("nan")), x)
        else:
            x = np.where(far, np.nan, x)
        return self.normalized_to_pixel(_stack([x, y], X))

    def pixel_grid(self, like=None):
        """All pixel centres as uv [H, W, 2] (float64 numpy, or a tensor like `like`)."""
        v, u = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64)
        uv = np.stack([u, v], axis=-1)
        return uv if like is None else const_like(uv, like)

    def in_image(self, uv):
        """Boolean mask [...]: the continuous coordinate lies within the pixel area of the image."""
        u, v = uv[..., 0], uv[..., 1]
        return (u >= -0.5) & (u <= self.width - 0.5) & (v >= -0.5) & (v <= self.height - 0.5)

    def scaled(self, factor: float) -> "Camera":
        """The same lens at a resolution scaled by `factor` (pixel centres stay consistent)."""
        K = self.K.copy()
        K[0, 0] *= factor
        K[1, 1] *= factor
        K[0, 2] = (K[0, 2] + 0.5) * factor - 0.5
        K[1, 2] = (K[1, 2] + 0.5) * factor - 0.5
        return self._replace(width=round(self.width * factor), height=round(self.height * factor), K=K)

    def _replace(self, **kw):
        d = dict(width=self.width, height=self.height, K=self.K, dist=self.dist)
        d.update(kw)
        return type(self)(**d)

    # --- serialisation ------------------------------------------------------------------------
    def to_dict(self) -> dict:
        return {
            "width": self.width,
            "height": self.height,
            "K": self.K.tolist(),
            "dist": self.dist.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict, what: str = "camera") -> "Camera":
        try:
            return cls(width=d["width"], height=d["height"], K=np.asarray(d["K"], dtype=np.float64), dist=d.get("dist"))
        except KeyError as e:
            raise CalibrationError(f"{what}: missing key {e.args[0]!r}") from None
        except (TypeError, ValueError) as e:
            if isinstance(e, CalibrationError):
                raise CalibrationError(f"{what}: {e}") from None
            raise CalibrationError(f"{what}: malformed entry ({e})") from None

    def describe(self) -> str:
        k = ", ".join(f"{c:.4g}" for c in self.dist)
        return (
            f"{self.width}x{self.height} px, fx={self.fx:.2f} fy={self.fy:.2f} "
            f"cx={self.cx:.2f} cy={self.cy:.2f}, dist=({k})"
        )


# the last few cameras' ray grids (camera_rays); the lock makes a second caller wait for a grid being computed
# (e.g. in scans.prefetch's thread) instead of computing it again
_RAYS_CACHE: dict = {}
_RAYS_LOCK = threading.Lock()


def camera_rays(camera: Camera, uv: np.ndarray | None = None) -> np.ndarray:
    """Unit ray directions [..., 3] (camera frame) of pixels uv [..., 2] (default: every pixel, [H, W, 3]; the
    last few cameras' grids are cached, read-only: undistorting every pixel costs more than a triangulation)."""
    if uv is not None:
        return camera.pixel_to_ray(np.asarray(uv, np.float64))
    with _RAYS_LOCK:
        return bounded_cache(_RAYS_CACHE, camera.cache_key, lambda: _read_only(_ray_grid(camera)))


def cache_rays(camera: Camera, rays: np.ndarray) -> None:
    """Hold `rays` [H, W, 3] (float64, as camera_rays computes them, e.g. in another process) as the camera's ray
    grid in camera_rays' cache."""
    rays = np.asarray(rays, np.float64)
    if rays.shape != (camera.height, camera.width, 3):
        raise ValueError(f"cache_rays: a ray grid of shape {rays.shape} for a {camera.width}x{camera.height} camera")
    with _RAYS_LOCK:
        bounded_cache(_RAYS_CACHE, camera.cache_key, lambda: _read_only(rays))


# the threads (bands of rows) a camera's ray grid is undistorted in, at most (and no more than the CPU count)
RAY_BANDS = 8


def _ray_grid(camera: Camera) -> np.ndarray:
    """[H, W, 3] float64: every pixel's ray, bands of rows undistorted in threads (numpy's array operations leave the
    interpreter lock free: 1280 x 1024 rays took 0.35-0.5 s in one thread, most of a fresh run's first depth search)."""
    from concurrent.futures import ThreadPoolExecutor

    uv = camera.pixel_grid()
    bands = np.array_split(np.arange(camera.height), min(os.cpu_count() or 1, RAY_BANDS, camera.height))
    if len(bands) < 2:
        return camera.pixel_to_ray(uv)
    out = np.empty((camera.height, camera.width, 3), np.float64)

    def band(rows: np.ndarray) -> None:
        out[rows[0] : rows[-1] + 1] = camera.pixel_to_ray(uv[rows[0] : rows[-1] + 1])

    with ThreadPoolExecutor(max_workers=len(bands)) as pool:
        list(pool.map(band, [b for b in bands if b.size]))
    return out


def _read_only(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False
    return a


def check_rotation(R: np.ndarray, what: str = "extrinsics R", tol: float = 1e-3) -> np.ndarray:
    """R as a 3x3 float64 rotation, or CalibrationError if not orthonormal with det +1 within `tol`."""
    R = np.asarray(R, dtype=np.float64)
    if R.size != 9:
        raise CalibrationError(f"{what}: must have 9 entries, got {R.size}")
    R = R.reshape(3, 3)
    if not np.all(np.isfinite(R)):
        raise CalibrationError(f"{what}: non-finite entries:\n{R}")
    err = np.abs(R @ R.T - np.eye(3)).max()
    det = np.linalg.det(R)
    if err > tol or abs(det - 1.0) > tol:
        raise CalibrationError(
            f"{what}: not a rotation (|R R^T - I| = {err:.3g}, det = {det:.6f}; need orthonormal with det +1)"
        )
    return R


@dataclass
class Projector(Camera):
    """A projector: an inverse camera with its pose. X_p = R X_c + T (mm), patterns in projector pixels."""

    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    T: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self):
        super().__post_init__()
        self.R = check_rotation(self.R, "projector extrinsics R")
        self.T = np.asarray(self.T, dtype=np.float64).ravel()
        if self.T.size != 3 or not np.all(np.isfinite(self.T)):
            raise CalibrationError(f"projector extrinsics T: need 3 finite values, got {self.T}")
        self.packed = PackedProjector.of(self)

    @property
    def center(self) -> np.ndarray:
        """Projector optical centre in the camera frame [3] (mm)."""
        return -self.R.T @ self.T

    @property
    def baseline(self) -> float:
        """Distance between the camera and projector centres (mm)."""
        return float(np.linalg.norm(self.T))

    def camera_to_projector(self, Xc):
        """Camera-frame points [..., 3] -> projector-frame points [..., 3]."""
        Xc = _as_float(Xc)
        return _rotate(Xc, self.R) + const_like(self.T, Xc)

    def project_camera_points(self, Xc):
        """Camera-frame points [..., 3] -> projector pixels [..., 2] (distorted; NaN behind the lens)."""
        return self.project(self.camera_to_projector(Xc))

    def pixel_to_ray_in_camera(self, uv):
        """Projector pixels [..., 2] -> unit ray directions [..., 3] in the camera frame."""
        d = self.pixel_to_ray(uv)
        return _rotate(d, self.R.T)

    def _replace(self, **kw):
        d = dict(width=self.width, height=self.height, K=self.K, dist=self.dist, R=self.R, T=self.T)
        d.update(kw)
        return type(self)(**d)

    def extrinsics_dict(self) -> dict:
        return {"R": self.R.tolist(), "T": self.T.tolist()}

    @classmethod
    def from_dicts(cls, intr: dict, extr: dict) -> "Projector":
        cam = Camera.from_dict(intr, "projector")
        try:
            R, T = extr["R"], extr["T"]
        except (KeyError, TypeError) as e:
            raise CalibrationError(f"extrinsics: missing key {e}") from None
        return cls(width=cam.width, height=cam.height, K=cam.K, dist=cam.dist, R=np.asarray(R, float), T=np.asarray(T, float))

    def describe(self) -> str:
        return super().describe() + f", baseline={self.baseline:.1f} mm"


class PackedProjector(NamedTuple):
    """A projector as 24 plain floats: the one layout that the Warp kernels (slwarp.kernels.geometry
    .projector_params), the torch ops (a custom op takes it as list[float]; torch.compile reads the tuple as a
    constant) and the torch twin share. Fields by name; `R`, `T` and `dist` regroup them."""

    r00: float
    r01: float
    r02: float
    r10: float
    r11: float
    r12: float
    r20: float
    r21: float
    r22: float
    tx: float  # mm
    ty: float
    tz: float
    fx: float  # px
    fy: float
    cx: float
    cy: float
    k1: float
    k2: float
    k3: float
    p1: float
    p2: float
    width: float  # px
    height: float
    max_r2: float  # trusted squared normalised radius of the distortion model (Camera.max_normalized_r2)

    @classmethod
    def of(cls, projector: "Projector") -> "PackedProjector":
        d = projector.dist
        return cls(*(float(x) for x in projector.R.ravel()), *(float(x) for x in projector.T), projector.fx, projector.fy,
                   projector.cx, projector.cy, float(d[0]), float(d[1]), float(d[4]), float(d[2]), float(d[3]),
                   float(projector.width), float(projector.height), float(projector.max_normalized_r2))

    @property
    def R(self) -> tuple:
        """X_p = R X_c + T: the rotation as 9 floats, row-major."""
        return tuple(self[0:9])

    @property
    def T(self) -> tuple:
        return (self.tx, self.ty, self.tz)

    @property
    def dist(self) -> tuple:
        """(k1, k2, p1, p2, k3): OpenCV's order, as `distort_normalized` takes it."""
        return (self.k1, self.k2, self.p1, self.p2, self.k3)


def look_at_rotation(position: np.ndarray, target: np.ndarray, up=(0.0, -1.0, 0.0)) -> np.ndarray:
    """Rotation R (world->device) of a device at `position` looking at `target`, OpenCV axes, y down."""
    z = np.asarray(target, float) - np.asarray(position, float)
    z /= np.linalg.norm(z)
    x = np.cross(-np.asarray(up, float), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z])  # rows: device axes expressed in world coordinates


def with_halo(patterns: np.ndarray, share: float, sigma: float, halo: np.ndarray | None = None) -> np.ndarray:
    """patterns [N, Hp, Wp] in [0, 1] as a lens with a halo shows them: (1 - share) x the pattern + share x the
    pattern Gaussian-blurred by `sigma` projector px (edges replicated; `halo`: that blur when the caller has
    it); share <= 0 returns them unchanged. The
    defocus (the simulator's, the pattern model's fitted blur) applies on top. Shared by the simulator
    (SimOptions.halo) and the neural method's pattern model (sampling.pattern_halo).

    Why: on the real capture the edge of a Gray code stripe is a Gaussian of about 0.7 projector px plus a halo of
    about 10% of the light spread over about 40 px (`python -m bench.edge_profile`): a dark stripe next to a wide
    bright one is brighter than next to a narrow one, which a Gaussian alone cannot give."""
    import cv2

    pats = np.asarray(patterns, np.float32)
    if share <= 0:
        return pats
    if halo is None:
        k = 2 * int(np.ceil(3.0 * sigma)) + 1
        halo = np.stack([cv2.GaussianBlur(p, (k, k), sigma, borderType=cv2.BORDER_REPLICATE) for p in pats])
    return ((1.0 - share) * pats + share * halo).astype(np.float32)
