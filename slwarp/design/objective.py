"""The design objective: how clearly each camera pixel's code picks its true depth on its epipolar line.

For a batch of random camera pixels r and true depths z* (uniform in inverse depth over the rig's depth range, so
uniform in projector px along the line), the camera sees

    o_n = a + b P~_n(pi(x*)) + noise_n                  n = 1..K frames

P~ the patterns blurred by the projector's defocus (`blur_px`; the camera's view at a blur drawn from a spread around
it, `NoiseModel.blur_spread`, the hypotheses' codes at `blur_px`), a the ambient offset, b the modulation (albedo,
fall-off, projector power), the noise the virtual scanner's (read noise and shot noise). A decoder that knows neither
a nor b normalises by the observation's own min and max, o^ = (o - min o) / (max o - min o), which is the pattern
model's offset and modulation (slwarp.neural.pattern_model) that the depth search and the neural SDF use, and
compares o^ with the code P~(pi(x_h)) of each depth hypothesis x_h along the ray. Under the noise, the posterior over
the hypotheses is

    p_h ∝ exp(-|o^ - P~(pi(x_h))|^2 / (2 s^2))          s: the noise in normalised units (times `softness`)

and the loss is the expected miss  sum_h p_h min(1, d_h / tol_px),  d_h the distance (projector px) between the
hypothesis' projector pixel and the true one: 0 when every pixel's code picks its own depth; 1 when it picks one more
than `tol_px` away. The search needs to land within a few px (the neural SDF refines from there), so a miss of many
px costs as much as one of `tol_px`. Gradients reach the pattern pixels through the bilinear reprojection
(`slwarp.neural.ops.reproject_patterns`: Warp kernels with a backward into the pattern image, or its torch twin).

With a window (`CodeModel.batch(..., window=R)`), each pixel comes with the (2R + 1)^2 camera pixels around it at its
depth, and a hypothesis' distance sums over them, each normalised by its own min and max: the depth search's cost,
which sums a window at one depth hypothesis (`start.search.search_depth`, R = 2). A window sees the code's shape along
the line, so 3 patterns can tell depths apart that one pixel's 3 values (one degree of freedom once normalised) cannot.

`CodeModel` holds what is fixed for a rig (rays, hypotheses); `miss_loss` evaluates one batch.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from ..neural.ops import twin

__all__ = ["NoiseModel", "CodeModel", "Batch", "miss_loss", "epipolar_span_px", "epipolar_direction", "code_image"]


@dataclass(frozen=True)
class NoiseModel:
    """What the camera adds to the code (intensities in full-scale units, as slwarp.sim.SimOptions).

    ambient: the offset a is drawn from [0, ambient]; modulation (lo, hi): b drawn from it (albedo x fall-off x
    projector power); read_noise: Gaussian std; full_well: electrons at full scale (shot noise); blur_px: Gaussian
    sigma of the projector's defocus and the camera pixel's footprint, in projector px, as the decoder models it;
    blur_spread: the blur the camera really sees lies anywhere in [blur_px / spread, blur_px x spread] (1: exactly
    blur_px). Why: defocus changes with depth and a pixel's footprint with the surface's slant, while a decoder
    models one blur; a design scored with the decoder's blur only may hang a code on a detail one projector pixel
    wide, which the camera sees at another strength (default rig, design of 4: one such column put 1,191 pixels of
    the spheres 490 mm off, their code matching a nearer depth better than their own)."""

    ambient: float = 0.08
    modulation: tuple[float, float] = (0.15, 0.8)
    read_noise: float = 0.004
    full_well: float = 6000.0
    blur_px: float = 1.0
    blur_spread: float = 2.0

    def __post_init__(self):
        lo, hi = self.modulation
        if not (0.0 < lo <= hi <= 1.0):
            raise ValueError(f"modulation range must satisfy 0 < lo <= hi <= 1, got {self.modulation}")
        if self.ambient < 0 or self.read_noise < 0 or self.full_well <= 0 or self.blur_px < 0:
            raise ValueError("ambient, read noise and blur must be >= 0 and full well > 0")
        if not self.blur_spread >= 1.0:
            raise ValueError(f"the blur's spread must be >= 1 (1: the blur exactly as modelled), got {self.blur_spread}")

    def observed_blurs(self, u: float | None = None) -> tuple[float, ...]:
        """The blurs (projector px) the camera is scored with: blur_px x spread^u for one draw u in [-1, 1], or,
        without one, the range's ends and middle (a validation's fixed set)."""
        if u is not None:
            return (self.blur_px * self.blur_spread ** u,)
        return tuple(dict.fromkeys(self.blur_px * self.blur_spread ** e for e in (-1.0, 0.0, 1.0)))


def _epipolar_segments(camera, projector, depth_range, grid: int = 24):
    """(near ends, far ends) [P, 2] projector px of the rays of a grid x grid lattice of camera pixels whose ray meets
    the projector image at both ends of the depth range."""
    u = np.linspace(0, camera.width - 1, grid)
    v = np.linspace(0, camera.height - 1, grid)
    uv = np.stack(np.meshgrid(u, v), -1).reshape(-1, 2)
    d = camera.pixel_to_ray(uv)
    ends = []
    for z in depth_range:
        p = projector.project_camera_points(d * (z / d[:, 2:3]))
        ends.append(p)
    a, b = ends
    inside = np.all(np.isfinite(a) & np.isfinite(b), axis=1)
    for p in (a, b):
        inside &= (p[:, 0] > -0.5) & (p[:, 0] < projector.width - 0.5) & (p[:, 1] > -0.5) & (p[:, 1] < projector.height - 0.5)
    if not inside.any():
        raise ValueError("no camera pixel sees the projector image at both ends of the depth range "
                         f"{depth_range[0]:g}-{depth_range[1]:g} mm: check the calibration and the depth range")
    return a[inside], b[inside]


def epipolar_span_px(camera, projector, depth_range, grid: int = 24) -> float:
    """The longest epipolar segment (projector px) that a camera pixel's ray draws across the depth range."""
    a, b = _epipolar_segments(camera, projector, depth_range, grid)
    return float(np.linalg.norm(a - b, axis=1).max())


def epipolar_direction(camera, projector, depth_range, grid: int = 24) -> np.ndarray:
    """The mean direction [2] (unit, projector px) in which a point moves on the projector image as its depth grows."""
    a, b = _epipolar_segments(camera, projector, depth_range, grid)
    d = b - a
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
    m = d.mean(0)
    return m / np.linalg.norm(m)


def code_image(codes: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
    """Pattern images [K, Hp, Wp] of 1-D codes [K, L] (one sample per px of the coordinate) at each projector pixel's
    coordinate coords [Hp, Wp] in [0, L - 1] (linear between samples; differentiable in the codes)."""
    L = codes.shape[1]
    i0 = coords.floor().clamp(0, L - 2)
    f = (coords - i0).clamp(0.0, 1.0)
    i0 = i0.long()
    flat = i0.reshape(-1)
    c0 = codes[:, flat].reshape(codes.shape[0], *coords.shape)
    c1 = codes[:, flat + 1].reshape(codes.shape[0], *coords.shape)
    return c0 + f * (c1 - c0)


@dataclass
class Batch:
    """One batch of M pixels, each with the Wn pixels of its window (Wn = 1 without one: the pixel alone): uv_true
    [M, Wn, 2] and uv_hyp [M, Wn, Hn, 2] projector px (a hypothesis off the projector image far outside it), lit
    [M, Wn] (the window pixel's true point lands on the projector image), dist [M, Hn] (projector px from the centre's
    true pixel), offset a [M], modulation b [M], noise [M, Wn, K] (standard normal draws, scaled by the noise model in
    `miss_loss`)."""

    uv_true: torch.Tensor
    uv_hyp: torch.Tensor
    lit: torch.Tensor
    dist: torch.Tensor
    offset: torch.Tensor
    modulation: torch.Tensor
    noise: torch.Tensor


class CodeModel:
    """A rig's geometry for the objective: camera, projector, depth range (camera z, mm), hypotheses every
    `step_px` projector px along each epipolar line (at most `max_hypotheses`), on `device`."""

    def __init__(self, camera, projector, depth_range, noise: NoiseModel, *, step_px: float = 0.5,
                 max_hypotheses: int = 2048, device="cpu"):
        near, far = (float(x) for x in depth_range)
        if not (0 < near < far):
            raise ValueError(f"depth range must be 0 < near < far (mm), got {near:g}-{far:g}")
        self.camera, self.projector, self.noise = camera, projector, noise
        self.depth_range = (near, far)
        self.device = torch.device(device)
        self.span_px = epipolar_span_px(camera, projector, (near, far))
        # the projector pixels' coordinate along the epipolar direction, from 0 (the codes' first sample)
        e = epipolar_direction(camera, projector, (near, far))
        self.direction = e
        v, u = np.indices((projector.height, projector.width), dtype=np.float64)
        t = u * e[0] + v * e[1]
        t -= t.min()
        self.code_length = int(math.ceil(t.max())) + 2
        self.coords = torch.as_tensor(t, dtype=torch.float32, device=self.device)
        self.hypotheses = int(min(max_hypotheses, max(16, math.ceil(self.span_px / step_px) + 1)))
        # hypotheses uniform in inverse depth: nearly uniform in projector px along the line
        t = torch.linspace(0.0, 1.0, self.hypotheses, dtype=torch.float64)
        self.z_hyp = (1.0 / (1.0 / near + t * (1.0 / far - 1.0 / near))).to(self.device, torch.float32)

    def _project(self, rays: torch.Tensor, z: torch.Tensor):
        """rays [M, 3] unit, z [M, ...] camera depth -> projector px [M, ..., 2] and lands-on-image mask [M, ...]."""
        shape = z.shape
        x = rays.reshape(rays.shape[0], *([1] * (len(shape) - 1)), 3) * (z / rays[:, 2].reshape(-1, *([1] * (len(shape) - 1))))[..., None]
        uv, ok = twin.project_to_projector(x, self.projector.packed)
        W, H = self.projector.width, self.projector.height
        ok = ok & (uv[..., 0] > -0.5) & (uv[..., 0] < W - 0.5) & (uv[..., 1] > -0.5) & (uv[..., 1] < H - 0.5)
        return uv, ok

    def batch(self, pixels: int, K: int, generator: torch.Generator, window: int = 0, step: int = 1) -> Batch:
        """A batch of up to `pixels` camera pixels whose true point lands on the projector image (the others are
        unlit: no code to design), each with the (2 window + 1)^2 camera pixels around it (window 0: itself only;
        `step` camera px apart) at its depth, as the depth search's window sums them (`start.search.search_depth`: one hypothesis depth for
        the whole window)."""
        dev = self.device
        g = generator
        cam = self.camera
        last = torch.tensor([cam.width - 1.0, cam.height - 1.0], dtype=torch.float64, device=dev)  # the last pixel
        uvc = torch.rand(pixels, 2, generator=g, device=dev, dtype=torch.float64) * last
        near, far = self.depth_range
        t = torch.rand(pixels, generator=g, device=dev)
        z_true = 1.0 / (1.0 / near + t * (1.0 / far - 1.0 / near))
        r = step * torch.arange(-window, window + 1, dtype=torch.float64, device=dev)
        offsets = torch.stack(torch.meshgrid(r, r, indexing="xy"), -1).reshape(-1, 2)  # [Wn, 2], the centre in the middle
        Wn = offsets.shape[0]
        uvw = torch.minimum(torch.clamp(uvc[:, None, :] + offsets[None], min=0.0), last)  # [P, Wn, 2], on the image
        rays = cam.pixel_to_ray(uvw.reshape(-1, 2)).to(torch.float32).reshape(pixels, Wn, 3)
        uv_true, lit = self._project(rays.reshape(-1, 3), z_true.repeat_interleave(Wn))
        uv_true, lit = uv_true.reshape(pixels, Wn, 2), lit.reshape(pixels, Wn)
        keep = lit[:, Wn // 2].nonzero()[:, 0]
        rays, uv_true, lit = rays[keep], uv_true[keep], lit[keep]
        M = rays.shape[0]
        uv_hyp, hit = self._project(rays.reshape(-1, 3), self.z_hyp.expand(M * Wn, -1))
        uv_hyp, hit = uv_hyp.reshape(M, Wn, -1, 2), hit.reshape(M, Wn, -1)
        dist = torch.linalg.norm(uv_hyp[:, Wn // 2] - uv_true[:, Wn // 2, None, :], dim=-1)
        # a hypothesis off the projector image sees no code; it stays a rival (its code is 0), as in the search
        lo, hi = self.noise.modulation
        b = lo + (hi - lo) * torch.rand(M, generator=g, device=dev)
        a = self.noise.ambient * torch.rand(M, generator=g, device=dev)
        return Batch(uv_true, torch.where(hit[..., None], uv_hyp, torch.full_like(uv_hyp, -1.0e6)), lit, dist, a, b,
                     torch.randn(M, Wn, K, generator=g, device=dev))


def miss_loss(patterns: torch.Tensor, batch: Batch, noise: NoiseModel, *, tol_px: float = 2.0,
              softness: float = 1.0, backend: str = "warp", details: bool = False, observed: torch.Tensor | None = None):
    """The expected miss (see the module docstring) of patterns [K, Hp, Wp] in [0, 1] (already blurred as the decoder
    models them) on one batch: a 0-d tensor, differentiable in the patterns. observed [K, Hp, Wp]: the patterns as the
    camera sees them (another blur; default: `patterns`), from which the observations come. With windows (batch.uv_true [M, Wn, 2],
    Wn > 1) each hypothesis' distance sums over the window's lit pixels, each normalised by its own min and max, as
    the depth search's cost. details=True also returns {"miss_rate": share of pixels whose most probable hypothesis
    is > tol_px away, "pixels": M}."""
    from ..neural.ops import reproject_patterns

    K = patterns.shape[0]
    M, Hn = batch.dist.shape
    Wn = batch.uv_true.shape[1]
    seen = patterns if observed is None else observed
    code_true = reproject_patterns(seen, batch.uv_true.reshape(-1, 2), backend=backend).reshape(M, Wn, K)
    clean = batch.offset[:, None, None] + batch.modulation[:, None, None] * code_true
    # the virtual scanner's noise: read noise and shot noise of the clean intensity, clipped to the sensor's range
    sd = torch.sqrt(noise.read_noise ** 2 + clean.detach().clamp_min(0.0) / noise.full_well)
    obs = (clean + sd * batch.noise).clamp(0.0, 1.0)
    lo = obs.min(2, keepdim=True).values
    span = obs.max(2, keepdim=True).values - lo
    obs_n = (obs - lo) / span.clamp_min(1.0e-3)  # [M, Wn, K]
    # the noise in normalised units (the window's centre's): what a pixel's code can be trusted to
    c = Wn // 2
    s = softness * sd[:, c].detach().mean(1, keepdim=True) / span[:, c].detach().clamp_min(0.02) * math.sqrt(2.0)
    codes = reproject_patterns(patterns, batch.uv_hyp.reshape(-1, 2), backend=backend).reshape(M, Wn, Hn, K)
    lit = batch.lit.to(codes.dtype)[:, :, None]  # window pixels whose point is off the projector image count nothing
    d2 = (((codes - obs_n[:, :, None, :]) ** 2).sum(-1) * lit).sum(1)  # [M, Hn]
    logp = torch.log_softmax(-d2 / (s * s), dim=1)
    miss = (batch.dist / tol_px).clamp(max=1.0)
    loss = (logp.exp() * miss).sum(1).mean()
    if not details:
        return loss
    wrong = batch.dist.gather(1, d2.argmin(1, keepdim=True))[:, 0] > tol_px
    return loss, {"miss_rate": float(wrong.float().mean()), "pixels": int(M)}
