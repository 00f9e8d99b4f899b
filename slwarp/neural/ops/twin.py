"""Pure-torch twins of the Warp ops, named after the ops in slwarp.neural.ops they mirror: the same semantics,
any dtype and device.

They are the reference in tests (compared with the Warp kernels forward and backward, and checked by
float64 gradcheck), the fallback backend (`backend="torch"`), and what torch.compile sees in benchmarks.
Formulas: see kernels/render.py and kernels/sampling.py; the constants are the kernels' own.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from ...scans.scanner import PackedProjector, const_like, distort_normalized
from slwarp.kernels.geometry import ALPHA_EPS, FAR_AWAY_PX, MIN_PROJECTOR_Z, TRANS_EPS
from slwarp.kernels.render import NORM_EPS, WSUM_EPS
from slwarp.kernels.sampling import CDF_EPS, MIN_SLOPE, PDF_EPS, SLOPE_EPS


# ----------------------------------------------------------------------------------------------
# projection and bilinear sampling


def project_to_projector(x: torch.Tensor, proj: PackedProjector) -> tuple[torch.Tensor, torch.Tensor]:
    """Camera-frame points [..., 3] -> projector pixels [..., 2] and ok mask [...].

    Points behind the lens or beyond the trusted distortion radius (proj.max_r2) are not ok; their pixel is
    far outside the image (so they sample zero).
    """
    R = const_like(proj.R, x).reshape(3, 3)
    T = const_like(proj.T, x)
    xp = (x[..., None, :] * R).sum(-1) + T  # x R^T, written out: a matmul would run in TF32 when that is on
    zp = xp[..., 2]
    in_front = zp > MIN_PROJECTOR_Z
    zs = torch.where(in_front, zp, torch.ones_like(zp))  # safe: no inf/NaN in either branch's gradient
    xn = xp[..., 0] / zs
    yn = xp[..., 1] / zs
    r2 = xn * xn + yn * yn
    ok = in_front & (r2 <= proj.max_r2)
    xn = torch.where(ok, xn, torch.zeros_like(xn))
    yn = torch.where(ok, yn, torch.zeros_like(yn))
    xd, yd = distort_normalized(xn, yn, proj.dist)
    far = torch.full_like(xd, FAR_AWAY_PX)
    u = torch.where(ok, proj.fx * xd + proj.cx, far)
    v = torch.where(ok, proj.fy * yd + proj.cy, far)
    return torch.stack([u, v], dim=-1), ok


def bilinear_patterns(patterns: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Bilinear values of all patterns [N, H, W] at projector pixels uv [..., 2] -> [..., N].

    Pixel centres at integer coordinates; taps outside the image count as zero. Written with explicit
    gathers (the same arithmetic as the kernel's), differentiable in uv.
    """
    N, H, W = patterns.shape
    lead = uv.shape[:-1]
    u = uv[..., 0].reshape(-1)
    v = uv[..., 1].reshape(-1)
    u0 = torch.floor(u)
    v0 = torch.floor(v)
    fu = u - u0
    fv = v - v0
    iu = u0.clamp(-2, W).long()  # clamping keeps far-away points' indices small; they stay outside
    iv = v0.clamp(-2, H).long()
    flat = patterns.reshape(N, H * W).to(uv.dtype)
    out = torch.zeros(N, u.shape[0], dtype=uv.dtype, device=uv.device)
    for dy in (0, 1):
        for dx in (0, 1):
            x = iu + dx
            y = iv + dy
            ok = (x >= 0) & (x < W) & (y >= 0) & (y < H)
            idx = torch.where(ok, y * W + x, torch.zeros_like(x))
            wgt = (fu if dx else 1.0 - fu) * (fv if dy else 1.0 - fv) * ok.to(uv.dtype)
            out = out + wgt[None, :] * flat[:, idx]
    return out.transpose(0, 1).reshape(*lead, N)


# ----------------------------------------------------------------------------------------------
# NeuS alpha and the fused render


def neus_alpha(sdf, true_cos, dz, inv_s, cos_anneal_ratio: float):
    """NeuS's discrete opacity of each sample's interval (see kernels/render.py)."""
    iter_cos = -(F.relu(-true_cos * 0.5 + 0.5) * (1.0 - cos_anneal_ratio) + F.relu(-true_cos) * cos_anneal_ratio)
    prev_cdf = torch.sigmoid((sdf - iter_cos * dz * 0.5) * inv_s)
    next_cdf = torch.sigmoid((sdf + iter_cos * dz * 0.5) * inv_s)
    return ((prev_cdf - next_cdf + ALPHA_EPS) / (prev_cdf + ALPHA_EPS)).clamp(0.0, 1.0)


def sample_intervals(z_vals: torch.Tensor, last_delta: float) -> torch.Tensor:
    """dz [R, S]: distance to the next sample; last: `last_delta` (>= 0) or the previous interval."""
    R, S = z_vals.shape
    if S == 1:
        return torch.full_like(z_vals, max(last_delta, 0.0))
    d = z_vals[:, 1:] - z_vals[:, :-1]
    last = torch.full_like(z_vals[:, :1], last_delta) if last_delta >= 0 else d[:, -1:]
    return torch.cat([d, last], dim=1)


def transmittance_weights(alpha: torch.Tensor) -> torch.Tensor:
    """w_k = alpha_k prod_{j<k} (1 - alpha_j + TRANS_EPS)."""
    # the product as exp(cumsum(log)): torch's cumprod backward checks the input for zeros on the host (a
    # synchronisation per step, and no CUDA graph capture); 1 - alpha + TRANS_EPS > 0, so the log is finite
    log_keep = torch.log(1.0 - alpha + TRANS_EPS)
    trans = torch.exp(torch.cumsum(torch.cat([torch.zeros_like(log_keep[:, :1]), log_keep[:, :-1]], dim=1), dim=1))
    return alpha * trans


def inside_box(x: torch.Tensor, bounds: list[float]) -> torch.Tensor:
    lo = const_like(bounds[0:3], x)
    hi = const_like(bounds[3:6], x)
    return ((x >= lo) & (x <= hi)).all(dim=-1)


def render_structured_light(sdf, sdf_grad, z_vals, rays_o, rays_d, a, b, patterns, projector: PackedProjector, inv_s,
                            cos_anneal_ratio: float, last_delta: float, bounds: list[float]):
    """The fused render in torch, on the inputs of ops.RenderInputs (any dtype) with patterns [N, H, W] and inv_s a
    tensor broadcastable to a scalar (differentiable). Returns (weights [R,S], rendered [R,N], surface [R,3],
    surface_rendered [R,N], depth [R], weight_sum [R], eikonal [R,S], eikonal_sum [R], eikonal_count [R]).
    """
    dz = sample_intervals(z_vals, last_delta)
    true_cos = (sdf_grad * rays_d[:, None, :]).sum(-1)
    alpha = neus_alpha(sdf, true_cos, dz, inv_s.reshape(()), cos_anneal_ratio)
    weights = transmittance_weights(alpha)
    x = rays_o[:, None, :] + z_vals[..., None] * rays_d[:, None, :]
    uv, _ = project_to_projector(x, projector)
    pat = bilinear_patterns(patterns, uv)  # [R, S, N]
    weight_sum = weights.sum(1)
    rendered = a[:, None] * weight_sum[:, None] + b[:, None] * (weights[..., None] * pat).sum(1)
    surface = (weights[..., None] * x).sum(1) / (weight_sum[:, None] + WSUM_EPS)
    uv_s, _ = project_to_projector(surface, projector)
    surface_rendered = a[:, None] + b[:, None] * bilinear_patterns(patterns, uv_s)
    inside = inside_box(x, bounds)
    nrm = torch.sqrt((sdf_grad * sdf_grad).sum(-1) + NORM_EPS)
    eikonal = torch.where(inside, (nrm - 1.0) ** 2, torch.zeros_like(nrm))
    return (weights, rendered, surface, surface_rendered, surface[:, 2], weight_sum, eikonal, eikonal.sum(1),
            inside.to(sdf.dtype).sum(1))


# ----------------------------------------------------------------------------------------------
# rays and samples


def camera_rays(pixels: torch.Tensor, camera, z_near: float, z_far: float):
    """pixels [R, 2] -> (rays_d [R, 3] unit, near [R], far [R]); near/far are distances along the ray."""
    d = camera.pixel_to_ray(pixels)
    return d, z_near / d[:, 2], z_far / d[:, 2]


def stratified_samples(near: torch.Tensor, far: torch.Tensor, n: int, jitter: torch.Tensor) -> torch.Tensor:
    """z [R, n] = near + (far - near) (k + 0.5 + jitter_r) / n."""
    k = torch.arange(n, dtype=near.dtype, device=near.device)
    return near[:, None] + (far - near)[:, None] * (k[None, :] + 0.5 + jitter[:, None]) / n


def upsample_samples(z: torch.Tensor, sdf: torch.Tensor, rays_o, rays_d, n_new: int, inv_s: float, bounds: list[float]) -> torch.Tensor:
    """One NeuS up-sampling step: n_new new sample distances [R, n_new] (sorted)."""
    R, S = z.shape
    x = rays_o[:, None, :] + z[..., None] * rays_d[:, None, :]
    inside = inside_box(x, bounds)
    inside_iv = inside[:, :-1] | inside[:, 1:]
    dist = z[:, 1:] - z[:, :-1]
    cos = (sdf[:, 1:] - sdf[:, :-1]) / (dist + SLOPE_EPS)
    prev_cos = torch.cat([torch.zeros_like(cos[:, :1]), cos[:, :-1]], dim=1)
    c = torch.minimum(prev_cos, cos).clamp(MIN_SLOPE, 0.0) * inside_iv
    mid = (sdf[:, 1:] + sdf[:, :-1]) * 0.5
    prev_cdf = torch.sigmoid((mid - c * dist * 0.5) * inv_s)
    next_cdf = torch.sigmoid((mid + c * dist * 0.5) * inv_s)
    alpha = (prev_cdf - next_cdf + ALPHA_EPS) / (prev_cdf + ALPHA_EPS)
    w = transmittance_weights(alpha) + PDF_EPS
    pdf = w / w.sum(1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[:, :1]), torch.cumsum(pdf, 1)], dim=1)  # [R, S]
    u = (torch.arange(n_new, dtype=z.dtype, device=z.device) + 0.5) / n_new
    u = u.expand(R, n_new).contiguous()
    idx = torch.searchsorted(cdf.contiguous(), u, right=True)
    below = (idx - 1).clamp(min=0)
    above = idx.clamp(max=S - 1)
    c0, c1 = cdf.gather(1, below), cdf.gather(1, above)
    z0, z1 = z.gather(1, below), z.gather(1, above)
    denom = c1 - c0
    denom = torch.where(denom < CDF_EPS, torch.ones_like(denom), denom)
    return z0 + (u - c0) / denom * (z1 - z0)


def merge_samples(z_a, f_a, z_b, f_b):
    """Merge two per-ray sorted lists (stable: ties keep a before b)."""
    z = torch.cat([z_a, z_b], dim=1)
    f = torch.cat([f_a, f_b], dim=1)
    z_sorted, order = torch.sort(z, dim=1, stable=True)
    return z_sorted, f.gather(1, order)
