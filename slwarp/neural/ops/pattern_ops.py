"""Pattern reprojection as a torch op (`reproject_patterns`): the bilinear values of K projector patterns at
projector pixels, differentiable in the patterns and the pixels, for pattern design (gradient descent on the
patterns through lookups at fixed projections of camera rays at depth hypotheses); importable from
slwarp.neural.ops.

backend="warp" (default: kernels/reproject.py, CPU or CUDA, float32; one forward and one hand-written backward
that scatters into the patterns with atomics, through a torch.autograd.Function) or "torch" (the twin
`twin.bilinear_patterns`: any dtype, differentiable by autograd).
"""
from __future__ import annotations

import torch

from . import twin
from .launch import check_backend, desc, f32, launch
from slwarp.kernels.reproject import reproject_kernels

__all__ = ["reproject_patterns"]


class _ReprojectFunction(torch.autograd.Function):
    """patterns_hwn [Hp, Wp, K] float32 contiguous, uv [M, 2] float32 (last axis contiguous) -> [M, K] float32."""

    @staticmethod
    def forward(ctx, patterns_hwn: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
        M, K = uv.shape[0], patterns_hwn.shape[2]
        out = torch.empty(M, K, dtype=torch.float32, device=uv.device)
        if M > 0 and K > 0:
            forward, _ = reproject_kernels(int(K))
            launch(forward, M, [desc(patterns_hwn), desc(uv, 2), desc(out)], uv.device)
        ctx.save_for_backward(patterns_hwn, uv)
        return out

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):
        patterns_hwn, uv = ctx.saved_tensors
        need_patterns, need_uv = ctx.needs_input_grad[:2]
        M, K = uv.shape[0], patterns_hwn.shape[2]
        dev = uv.device
        # the scatter adds into it: zeros, not empty
        g_pat = torch.zeros_like(patterns_hwn) if need_patterns else None
        g_uv = torch.empty(M, 2, dtype=torch.float32, device=dev) if need_uv else None
        if M > 0 and K > 0 and (need_patterns or need_uv):
            _, backward = reproject_kernels(int(K))
            # an unneeded output gets a stand-in the kernel never writes (a launch takes arrays in every place)
            launch(backward, M, [desc(patterns_hwn), desc(uv, 2), desc(f32(grad_out)), int(need_patterns), int(need_uv),
                                 desc(g_pat if need_patterns else patterns_hwn[:0]),
                                 desc(g_uv if need_uv else uv[:0], 2)], dev)
        elif need_uv:
            g_uv.zero_()
        return g_pat, g_uv


def reproject_patterns(patterns: torch.Tensor, uv: torch.Tensor, *, backend: str = "warp") -> torch.Tensor:
    """Bilinear values of K patterns at projector pixels.

    patterns [K, Hp, Wp] (intensities, any float dtype for backend="torch"); uv [..., 2] (u, v) in projector
    pixels on the same device, pixel centres at integer coordinates. Returns [..., K]: taps outside the image
    count as zero, so uv farther than a pixel outside gives 0; with backend="warp" a NaN uv gives 0 too (the
    twin gives NaN).

    Differentiable in patterns and uv (bilinear is not differentiable at integer u or v: there the gradient
    into uv is the one-sided one of the cell floor(u), floor(v)). backend "warp" computes in float32 on the
    inputs' device (CPU or CUDA, on torch's current stream, no host synchronisation) and returns float32
    (gradients come back in the inputs' dtypes); "torch" computes in uv's dtype.
    """
    check_backend(backend)
    if patterns.dim() != 3:
        raise ValueError(f"patterns must be [K, Hp, Wp], got {tuple(patterns.shape)}")
    if uv.shape[-1:] != (2,):
        raise ValueError(f"uv must be [..., 2], got {tuple(uv.shape)}")
    if patterns.device != uv.device:
        raise ValueError(f"patterns and uv must be on the same device, got {patterns.device} and {uv.device}")
    if backend == "torch":
        return twin.bilinear_patterns(patterns, uv)
    K = patterns.shape[0]
    lead = uv.shape[:-1]
    # differentiable conversions outside the Function: autograd takes the gradients back through the transpose
    # and the casts, so the kernels see float32 [Hp, Wp, K] (the K values of a pixel side by side)
    pat_hwn = patterns.to(torch.float32).permute(1, 2, 0).contiguous()
    uv2 = uv.reshape(-1, 2).to(torch.float32)
    uv2 = uv2 if uv2.stride(-1) == 1 else uv2.contiguous()
    out = _ReprojectFunction.apply(pat_hwn, uv2)
    return out.reshape(*lead, K)
