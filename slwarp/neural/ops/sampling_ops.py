"""Torch-facing ray and sample ops (no gradients flow through them), each with a pure-torch twin in
slwarp.neural.ops.twin; importable from slwarp.neural.ops with the renderer. Kernels: kernels/sampling.py.

    camera_rays(...)              pixels -> rays and near/far distances
    stratified_samples(...)       stratified samples with per-ray jitter
    upsample_samples(...)         one NeuS hierarchical up-sampling step
    merge_samples(...)            merge two sorted per-ray sample lists

backend="warp" (default: Warp kernels, CPU or CUDA, float32) or "torch" (the twin: any dtype).
"""
from __future__ import annotations

import torch

from . import twin
from .launch import bounds_list, camera_struct, check_backend, desc, f32, f32v, launch, vec3
from slwarp.kernels.sampling import camera_rays as camera_rays_kernel
from slwarp.kernels.sampling import merge_sorted as merge_sorted_kernel
from slwarp.kernels.sampling import stratified as stratified_kernel
from slwarp.kernels.sampling import upsample_intervals as upsample_intervals_kernel
from slwarp.kernels.sampling import upsample_place as upsample_place_kernel

__all__ = ["camera_rays", "stratified_samples", "upsample_samples", "merge_samples"]


def camera_rays(pixels: torch.Tensor, camera, depth_range, *, backend: str = "warp"):
    """Rays through camera pixels.

    pixels [R, 2] (u, v) in camera pixels; depth_range (z_near, z_far) in mm of camera z.
    Returns rays_o [R, 3] (zeros: the camera centre), rays_d [R, 3] unit (undistorted), near [R] and
    far [R]: distances along each ray where it reaches z_near and z_far.
    """
    check_backend(backend)
    z_near, z_far = (float(x) for x in depth_range)
    R = pixels.shape[0]
    if backend == "torch" or R == 0:
        d, near, far = twin.camera_rays(pixels, camera, z_near, z_far)
    else:
        dev = pixels.device
        d = torch.empty(R, 3, dtype=torch.float32, device=dev)
        near = torch.empty(R, dtype=torch.float32, device=dev)
        far = torch.empty(R, dtype=torch.float32, device=dev)
        launch(camera_rays_kernel, R, [desc(f32v(pixels), 2), camera_struct(camera), z_near, z_far,
                                       desc(d, 3), desc(near), desc(far)], dev)
    return torch.zeros_like(d), d, near, far


def stratified_samples(near: torch.Tensor, far: torch.Tensor, n: int, jitter: torch.Tensor | None = None,
                       *, backend: str = "warp") -> torch.Tensor:
    """z [R, n]: near + (far - near) (k + 0.5 + jitter_r) / n; jitter [R] in [-0.5, 0.5) (None: 0)."""
    check_backend(backend)
    R = near.shape[0]
    if jitter is None:
        jitter = torch.zeros_like(near)
    if backend == "torch" or R == 0:
        return twin.stratified_samples(near, far, n, jitter)
    z = torch.empty(R, n, dtype=torch.float32, device=near.device)
    launch(stratified_kernel, (R, n), [desc(f32(near)), desc(f32(far)), desc(f32(jitter)), desc(z)], near.device)
    return z


def upsample_samples(z_vals: torch.Tensor, sdf: torch.Tensor, rays_o: torch.Tensor, rays_d: torch.Tensor,
                     n_new: int, inv_s: float, *, bounds=None, backend: str = "warp") -> torch.Tensor:
    """One NeuS up-sampling step: n_new new sorted distances [R, n_new] placed by inverse CDF of NeuS's
    estimated weights from the SDF at the current samples with a fixed inv_s (1/mm)."""
    check_backend(backend)
    bnd = bounds_list(bounds)
    R = z_vals.shape[0]
    if backend == "torch" or R == 0:
        return twin.upsample_samples(z_vals, sdf, rays_o, rays_d, n_new, float(inv_s), bnd)
    S = z_vals.shape[1]
    if S == 0:
        raise ValueError("upsample_samples needs at least one sample per ray")
    dev = z_vals.device
    z = f32(z_vals)
    z_new = torch.empty(R, n_new, dtype=torch.float32, device=dev)
    # scratch: the alpha of each interval (its shape is fixed by the inputs: graph-capturable). Row-major: the
    # n_new threads of a ray walk the same row in step, and its few cache lines stay in L1 after the first load
    alpha = torch.empty(R, S - 1, dtype=torch.float32, device=dev)
    if S > 1:
        launch(upsample_intervals_kernel, (R, S - 1), [desc(z), desc(f32(sdf)), desc(f32v(rays_o), 3),
               desc(f32v(rays_d), 3), float(inv_s), vec3(bnd[0:3]), vec3(bnd[3:6]), desc(alpha)], dev)
    if n_new > 0:
        launch(upsample_place_kernel, (R, n_new), [desc(z), desc(alpha), desc(z_new)], dev)
    return z_new


def merge_samples(z_a: torch.Tensor, f_a: torch.Tensor, z_b: torch.Tensor, f_b: torch.Tensor, *, backend: str = "warp"):
    """Merge two per-ray sorted sample lists (distances z and values f) -> (z [R, Sa+Sb], f)."""
    check_backend(backend)
    R = z_a.shape[0]
    if backend == "torch" or R == 0:
        return twin.merge_samples(z_a, f_a, z_b, f_b)
    n = z_a.shape[1] + z_b.shape[1]
    z = torch.empty(R, n, dtype=torch.float32, device=z_a.device)
    f = torch.empty(R, n, dtype=torch.float32, device=z_a.device)
    if n == 0:
        return z, f
    launch(merge_sorted_kernel, (R, n), [desc(f32(z_a)), desc(f32(f_a)), desc(f32(z_b)), desc(f32(f_b)), desc(z), desc(f)], z_a.device)
    return z, f
