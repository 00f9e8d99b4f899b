"""Torch-facing ops: the Warp kernels wrapped as torch custom ops, with a pure-torch twin each.

Public functions take `backend="warp"` (default: fused Warp kernels, CPU or CUDA, float32) or
`backend="torch"` (the twin in slwarp.twin: any dtype, differentiable by autograd).

    render_structured_light(...)  the fused renderer (differentiable in sdf, sdf_grad and inv_s)
    camera_rays(...)              pixels -> rays and near/far distances
    stratified_samples(...)       stratified samples with per-ray jitter
    upsample_samples(...)         one NeuS hierarchical up-sampling step
    merge_samples(...)            merge two sorted per-ray sample lists

The Warp render is registered with torch.library.custom_op (+ register_fake, register_autograd), so it
composes with autograd and stays opaque (no graph break) under torch.compile.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from . import twin
from .kernels import runtime

__all__ = [
    "RenderOutput",
    "render_structured_light",
    "camera_rays",
    "stratified_samples",
    "upsample_samples",
    "merge_samples",
    "pack_projector",
    "pack_patterns",
]

BACKENDS = ("warp", "torch")


class RenderOutput(NamedTuple):
    """Result of `render_structured_light` (R rays, S samples, N patterns).

    rendered [R, N]: volume-rendered intensities sum_k w_k (a + b P_n(pi(x_k)));
    surface_points [R, 3]: expected surface point sum_k w_k x_k (camera frame, mm);
    surface_rendered [R, N]: a + b P_n(pi(surface point));
    weights [R, S]: NeuS weights; depth [R]: camera-frame z of the surface point (mm);
    eikonal [R, S]: (|grad f| - 1)^2 inside the working volume, 0 outside;
    weight_sum [R]: sum_k w_k (opacity of the ray); eikonal_count [R]: samples inside the volume.
    """

    rendered: torch.Tensor
    surface_points: torch.Tensor
    surface_rendered: torch.Tensor
    weights: torch.Tensor
    depth: torch.Tensor
    eikonal: torch.Tensor
    weight_sum: torch.Tensor
    eikonal_count: torch.Tensor


def _check_backend(backend: str):
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")


@torch._dynamo.assume_constant_result  # a rig is constant during a compiled run: no tracing into numpy
def pack_projector(projector) -> list[float]:
    """A `slwarp.Projector` as 24 floats: R (9, row-major), T (3), fx, fy, cx, cy, k1, k2, k3, p1, p2,
    width, height, max_r2 (the trusted squared normalised radius of its distortion model)."""
    if isinstance(projector, (list, tuple)):
        if len(projector) != 24:
            raise ValueError(f"a packed projector has 24 floats, got {len(projector)}")
        return [float(x) for x in projector]
    d = projector.dist
    return [float(x) for x in np.asarray(projector.R).ravel()] + [float(x) for x in np.asarray(projector.T)] + [
        projector.fx, projector.fy, projector.cx, projector.cy, float(d[0]), float(d[1]), float(d[4]),
        float(d[2]), float(d[3]), float(projector.width), float(projector.height), float(projector.max_normalized_r2),
    ]


@torch._dynamo.assume_constant_result
def _bounds_list(bounds) -> list[float]:
    """[xmin, ymin, zmin, xmax, ymax, zmax] (mm) of the working volume; None = unbounded."""
    if bounds is None:
        return [-3.0e38, -3.0e38, -3.0e38, 3.0e38, 3.0e38, 3.0e38]
    b = np.asarray(bounds.detach().cpu() if isinstance(bounds, torch.Tensor) else bounds, np.float64).reshape(-1)
    if b.size != 6:
        raise ValueError(f"bounds must be [[xmin, ymin, zmin], [xmax, ymax, zmax]], got {b.size} numbers")
    return [float(x) for x in b]


def pack_patterns(patterns: torch.Tensor) -> torch.Tensor:
    """[N, H, W] -> contiguous float32 [H, W, N]: the N values of a projector pixel side by side."""
    return patterns.detach().to(torch.float32).permute(1, 2, 0).contiguous()


# ----------------------------------------------------------------------------------------------
# Warp launches


def _wp_params(projector: list[float]):
    from .kernels.geometry import ProjectorParams

    wp = runtime.init()
    prm = ProjectorParams()
    prm.R = wp.mat33(*projector[0:9])
    prm.T = wp.vec3(*projector[9:12])
    prm.f = wp.vec2(projector[12], projector[13])
    prm.c = wp.vec2(projector[14], projector[15])
    prm.k = wp.vec3(projector[16], projector[17], projector[18])
    prm.p = wp.vec2(projector[19], projector[20])
    prm.size = wp.vec2(projector[21], projector[22])
    prm.max_r2 = projector[23]
    return prm


def _wp(t: torch.Tensor, dtype=None):
    wp = runtime.init()
    return wp.from_torch(t.detach(), dtype=dtype) if dtype is not None else wp.from_torch(t.detach())


_STREAMS: dict = {}


def _launch(kernel, dim, inputs, device: torch.device):
    """Launch on torch's current stream of `device` (no host synchronisation)."""
    wp = runtime.init()
    if device.type == "cuda":
        key = (device.index, torch.cuda.current_stream(device).cuda_stream)
        stream = _STREAMS.get(key)
        if stream is None:
            stream = _STREAMS[key] = wp.stream_from_torch(torch.cuda.current_stream(device))
        wp.launch(kernel, dim=dim, inputs=inputs, device=runtime.warp_device(device), stream=stream)
    else:
        wp.launch(kernel, dim=dim, inputs=inputs, device="cpu")


def _f32(t: torch.Tensor) -> torch.Tensor:
    return t.detach().to(torch.float32).contiguous()


@torch.library.custom_op("slwarp::render_forward", mutates_args=())
def _render_forward(
    sdf: torch.Tensor, sdf_grad: torch.Tensor, z_vals: torch.Tensor, rays_o: torch.Tensor, rays_d: torch.Tensor,
    a: torch.Tensor, b: torch.Tensor, patterns_hwn: torch.Tensor, projector: list[float], inv_s: torch.Tensor,
    cos_anneal_ratio: float, last_delta: float, bounds: list[float],
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    from .kernels.render import render_kernels

    wp = runtime.init()
    R, S = z_vals.shape
    N = patterns_hwn.shape[2]
    dev = z_vals.device
    opts = dict(dtype=torch.float32, device=dev)
    weights = torch.empty(R, S, **opts)
    rendered = torch.empty(R, N, **opts)
    surface = torch.empty(R, 3, **opts)
    surface_rendered = torch.empty(R, N, **opts)
    depth = torch.empty(R, **opts)
    weight_sum = torch.empty(R, **opts)
    eikonal = torch.empty(R, S, **opts)
    eikonal_count = torch.empty(R, **opts)
    if R > 0:
        fwd, _ = render_kernels(int(N))
        _launch(fwd, R, [
            _wp(sdf), _wp(sdf_grad, wp.vec3), _wp(z_vals), _wp(rays_o, wp.vec3), _wp(rays_d, wp.vec3), _wp(a), _wp(b),
            _wp(patterns_hwn), _wp_params(projector), _wp(inv_s), float(cos_anneal_ratio), float(last_delta),
            wp.vec3(*bounds[0:3]), wp.vec3(*bounds[3:6]),
            _wp(weights), _wp(rendered), _wp(surface, wp.vec3), _wp(surface_rendered), _wp(depth), _wp(weight_sum),
            _wp(eikonal), _wp(eikonal_count),
        ], dev)
    return weights, rendered, surface, surface_rendered, depth, weight_sum, eikonal, eikonal_count


@_render_forward.register_fake
def _(sdf, sdf_grad, z_vals, rays_o, rays_d, a, b, patterns_hwn, projector, inv_s, cos_anneal_ratio, last_delta, bounds):
    R, S = z_vals.shape
    N = patterns_hwn.shape[2]
    e = lambda *shape: z_vals.new_empty(shape, dtype=torch.float32)  # noqa: E731
    return e(R, S), e(R, N), e(R, 3), e(R, N), e(R), e(R), e(R, S), e(R)


@torch.library.custom_op("slwarp::render_backward", mutates_args=())
def _render_backward(
    sdf: torch.Tensor, sdf_grad: torch.Tensor, z_vals: torch.Tensor, rays_o: torch.Tensor, rays_d: torch.Tensor,
    a: torch.Tensor, b: torch.Tensor, patterns_hwn: torch.Tensor, projector: list[float], inv_s: torch.Tensor,
    cos_anneal_ratio: float, last_delta: float, bounds: list[float],
    g_weights: torch.Tensor, g_rendered: torch.Tensor, g_surface: torch.Tensor, g_surface_rendered: torch.Tensor,
    g_depth: torch.Tensor, g_weight_sum: torch.Tensor, g_eikonal: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    from .kernels.render import render_kernels

    wp = runtime.init()
    R, S = z_vals.shape
    N = patterns_hwn.shape[2]
    dev = z_vals.device
    d_sdf = torch.empty(R, S, dtype=torch.float32, device=dev)
    d_grad = torch.empty(R, S, 3, dtype=torch.float32, device=dev)
    d_inv_s = torch.empty(R, dtype=torch.float32, device=dev)
    if R > 0:
        _, bwd = render_kernels(int(N))
        _launch(bwd, R, [
            _wp(sdf), _wp(sdf_grad, wp.vec3), _wp(z_vals), _wp(rays_o, wp.vec3), _wp(rays_d, wp.vec3), _wp(a), _wp(b),
            _wp(patterns_hwn), _wp_params(projector), _wp(inv_s), float(cos_anneal_ratio), float(last_delta),
            wp.vec3(*bounds[0:3]), wp.vec3(*bounds[3:6]),
            _wp(g_weights), _wp(g_rendered), _wp(g_surface, wp.vec3), _wp(g_surface_rendered), _wp(g_depth),
            _wp(g_weight_sum), _wp(g_eikonal),
            _wp(d_sdf), _wp(d_grad, wp.vec3), _wp(d_inv_s),
        ], dev)
    return d_sdf, d_grad, d_inv_s.sum().reshape(1)


@_render_backward.register_fake
def _(sdf, sdf_grad, z_vals, *args):
    R, S = z_vals.shape
    return z_vals.new_empty(R, S), z_vals.new_empty(R, S, 3), z_vals.new_empty(1)


def _setup_context(ctx, inputs, output):
    sdf, sdf_grad, z_vals, rays_o, rays_d, a, b, patterns_hwn, projector, inv_s, anneal, last_delta, bounds = inputs
    ctx.save_for_backward(sdf, sdf_grad, z_vals, rays_o, rays_d, a, b, patterns_hwn, inv_s)
    ctx.params = (projector, anneal, last_delta, bounds)


def _backward(ctx, g_weights, g_rendered, g_surface, g_srend, g_depth, g_wsum, g_eik, _g_count):
    sdf, sdf_grad, z_vals, rays_o, rays_d, a, b, patterns_hwn, inv_s = ctx.saved_tensors
    projector, anneal, last_delta, bounds = ctx.params
    R, S = z_vals.shape
    N = patterns_hwn.shape[2]

    def cot(g, *shape):
        return _f32(g) if g is not None else z_vals.new_zeros(shape, dtype=torch.float32)

    d_sdf, d_grad, d_inv_s = _render_backward(
        sdf, sdf_grad, z_vals, rays_o, rays_d, a, b, patterns_hwn, projector, inv_s, anneal, last_delta, bounds,
        cot(g_weights, R, S), cot(g_rendered, R, N), cot(g_surface, R, 3), cot(g_srend, R, N), cot(g_depth, R),
        cot(g_wsum, R), cot(g_eik, R, S),
    )
    return d_sdf, d_grad, None, None, None, None, None, None, None, d_inv_s, None, None, None


_render_forward.register_autograd(_backward, setup_context=_setup_context)


# ----------------------------------------------------------------------------------------------
# public API


def render_structured_light(
    sdf: torch.Tensor,
    sdf_grad: torch.Tensor,
    z_vals: torch.Tensor,
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
    a: torch.Tensor,
    b: torch.Tensor,
    patterns: torch.Tensor,
    projector,
    inv_s,
    *,
    cos_anneal_ratio: float = 1.0,
    backend: str = "warp",
    bounds=None,
    last_delta: float | None = None,
    patterns_layout: str = "NHW",
) -> RenderOutput:
    """Render structured-light intensities of R rays from an SDF sampled at S points per ray.

    sdf [R, S] (mm) and sdf_grad [R, S, 3] are the field and its gradient at x_k = rays_o + z_vals[:, k]
    rays_d (z_vals [R, S] sorted distances in mm along unit rays_d [R, 3], camera frame); a, b [R] are the
    pixel's offset and modulation (I = a + b P); patterns [N, H, W] in [0, 1] in projector pixels (or
    [H, W, N] with patterns_layout="HWN", as `pack_patterns` makes); projector: a `slwarp.Projector` (or
    `pack_projector` of one); inv_s: the NeuS inverse standard deviation (1/mm; tensor or float).
    bounds: [[xmin, ymin, zmin], [xmax, ymax, zmax]] of the working volume where the Eikonal term counts
    (None: everywhere). last_delta: length of the last sample's interval (None: the previous interval).

    Differentiable in sdf, sdf_grad and inv_s (not in z_vals, rays, a, b or patterns).
    backend "warp" computes in float32 on the inputs' device; "torch" in the inputs' dtype.
    """
    _check_backend(backend)
    if z_vals.dim() != 2:
        raise ValueError(f"z_vals must be [R, S], got {tuple(z_vals.shape)}")
    R, S = z_vals.shape
    if sdf.shape != (R, S) or sdf_grad.shape != (R, S, 3):
        raise ValueError(f"sdf must be [R, S] = {(R, S)} and sdf_grad [R, S, 3]; got {tuple(sdf.shape)}, {tuple(sdf_grad.shape)}")
    if rays_o.shape != (R, 3) or rays_d.shape != (R, 3) or a.shape != (R,) or b.shape != (R,):
        raise ValueError("rays_o, rays_d must be [R, 3] and a, b [R]")
    if patterns.dim() != 3:
        raise ValueError(f"patterns must be 3-D, got {tuple(patterns.shape)}")
    if patterns_layout not in ("NHW", "HWN"):
        raise ValueError("patterns_layout must be 'NHW' or 'HWN'")
    proj = pack_projector(projector)
    bnd = _bounds_list(bounds)
    ld = -1.0 if last_delta is None else float(last_delta)
    if not isinstance(inv_s, torch.Tensor):
        inv_s = torch.tensor(float(inv_s), device=z_vals.device)
    if backend == "torch":
        pat_nhw = patterns if patterns_layout == "NHW" else patterns.permute(2, 0, 1)
        outs = twin.render(sdf, sdf_grad, z_vals, rays_o, rays_d, a, b, pat_nhw, proj, inv_s, float(cos_anneal_ratio), ld, bnd)
    else:
        pat_hwn = pack_patterns(patterns) if patterns_layout == "NHW" else patterns.detach().to(torch.float32).contiguous()
        outs = _render_forward(
            sdf.to(torch.float32).contiguous(), sdf_grad.to(torch.float32).contiguous(), _f32(z_vals), _f32(rays_o),
            _f32(rays_d), _f32(a), _f32(b), pat_hwn, proj, inv_s.to(torch.float32).reshape(1),
            float(cos_anneal_ratio), ld, bnd,
        )
    weights, rendered, surface, surface_rendered, depth, weight_sum, eikonal, eikonal_count = outs
    return RenderOutput(rendered, surface, surface_rendered, weights, depth, eikonal, weight_sum, eikonal_count)


def camera_rays(pixels: torch.Tensor, camera, depth_range, *, backend: str = "warp"):
    """Rays through camera pixels.

    pixels [R, 2] (u, v) in camera pixels; depth_range (z_near, z_far) in mm of camera z.
    Returns rays_o [R, 3] (zeros: the camera centre), rays_d [R, 3] unit (undistorted), near [R] and
    far [R]: distances along each ray where it reaches z_near and z_far.
    """
    _check_backend(backend)
    z_near, z_far = (float(x) for x in depth_range)
    R = pixels.shape[0]
    if backend == "torch" or R == 0:
        d, near, far = twin.camera_rays(pixels, camera, z_near, z_far)
    else:
        from .kernels.geometry import camera_params
        from .kernels.sampling import camera_rays as kernel

        wp = runtime.init()
        dev = pixels.device
        d = torch.empty(R, 3, dtype=torch.float32, device=dev)
        near = torch.empty(R, dtype=torch.float32, device=dev)
        far = torch.empty(R, dtype=torch.float32, device=dev)
        _launch(kernel, R, [_wp(_f32(pixels), wp.vec2), camera_params(camera), z_near, z_far,
                            _wp(d, wp.vec3), _wp(near), _wp(far)], dev)
    return torch.zeros_like(d), d, near, far


def stratified_samples(near: torch.Tensor, far: torch.Tensor, n: int, jitter: torch.Tensor | None = None,
                       *, backend: str = "warp") -> torch.Tensor:
    """z [R, n]: near + (far - near) (k + 0.5 + jitter_r) / n; jitter [R] in [-0.5, 0.5) (None: 0)."""
    _check_backend(backend)
    R = near.shape[0]
    if jitter is None:
        jitter = torch.zeros_like(near)
    if backend == "torch" or R == 0:
        return twin.stratified(near, far, n, jitter)
    from .kernels.sampling import stratified as kernel

    z = torch.empty(R, n, dtype=torch.float32, device=near.device)
    _launch(kernel, (R, n), [_wp(_f32(near)), _wp(_f32(far)), _wp(_f32(jitter)), _wp(z)], near.device)
    return z


def upsample_samples(z_vals: torch.Tensor, sdf: torch.Tensor, rays_o: torch.Tensor, rays_d: torch.Tensor,
                     n_new: int, inv_s: float, *, bounds=None, backend: str = "warp") -> torch.Tensor:
    """One NeuS up-sampling step: n_new new sorted distances [R, n_new] placed by inverse CDF of NeuS's
    estimated weights from the SDF at the current samples with a fixed inv_s (1/mm)."""
    _check_backend(backend)
    bnd = _bounds_list(bounds)
    R = z_vals.shape[0]
    if backend == "torch" or R == 0:
        return twin.upsample(z_vals, sdf, rays_o, rays_d, n_new, float(inv_s), bnd)
    from .kernels.sampling import upsample as kernel

    wp = runtime.init()
    z_new = torch.empty(R, n_new, dtype=torch.float32, device=z_vals.device)
    _launch(kernel, R, [_wp(_f32(z_vals)), _wp(_f32(sdf)), _wp(_f32(rays_o), wp.vec3), _wp(_f32(rays_d), wp.vec3),
                        float(inv_s), wp.vec3(*bnd[0:3]), wp.vec3(*bnd[3:6]), _wp(z_new)], z_vals.device)
    return z_new


def merge_samples(z_a: torch.Tensor, f_a: torch.Tensor, z_b: torch.Tensor, f_b: torch.Tensor, *, backend: str = "warp"):
    """Merge two per-ray sorted sample lists (distances z and values f) -> (z [R, Sa+Sb], f)."""
    _check_backend(backend)
    R = z_a.shape[0]
    if backend == "torch" or R == 0:
        return twin.merge_sorted(z_a, f_a, z_b, f_b)
    from .kernels.sampling import merge_sorted as kernel

    n = z_a.shape[1] + z_b.shape[1]
    z = torch.empty(R, n, dtype=torch.float32, device=z_a.device)
    f = torch.empty(R, n, dtype=torch.float32, device=z_a.device)
    _launch(kernel, R, [_wp(_f32(z_a)), _wp(_f32(f_a)), _wp(_f32(z_b)), _wp(_f32(f_b)), _wp(z), _wp(f)], z_a.device)
    return z, f
