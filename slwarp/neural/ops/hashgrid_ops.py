"""The multiresolution hash-grid encoding as torch ops (kernels/hashgrid.py has the formulas): a Warp backend
(autograd.Functions when eager, torch custom ops under torch.compile, so no graph breaks; CUDA-graph capture;
float32) and a pure-torch twin
(gathers, any dtype, differentiable by autograd) with the same signature and semantics.

    hashgrid_encode(x, table, meta, active)        features [P, L F] of unit-cube points x [P, 3]
    hashgrid_gradient(x, table, g, meta, active)   sum_j g_j d feat_j / dx [P, 3]

meta [L, 4] int32 comes from `slwarp.neural.fields.hashgrid.HashGridLayout.meta`; the field (`HashGridSDF`) is in
slwarp.neural.fields.hashgrid, which re-exports both ops.
"""
from __future__ import annotations

import torch

from .launch import check_backend, desc, launch, struct
from slwarp.kernels import runtime

__all__ = ["hashgrid_encode", "hashgrid_gradient", "twin_encode", "twin_gradient"]

PRIMES = (1, 2654435761, 805459861)  # Instant-NGP's spatial hash
# consecutive points one thread of the encoding's backward takes, summing in registers while they share a cell
# (kernels/hashgrid.py): samples along a ray share the coarse levels' cells, and same-address atomics serialise.
# H100, accurate preset, all levels on: 4.39 / 4.20 / 4.19 ms per step with runs of 1 / 8 / 32
BACKWARD_RUN = 8


# ----------------------------------------------------------------------------------------------
# the pure-torch twin (gathers; any dtype; autograd differentiates it in x, the table and g)


def _twin_geometry(x: torch.Tensor, meta: torch.Tensor, active: torch.Tensor):
    """Per point and level: the table rows of the 8 corners [P, L, 8] (long; corner c = x bit + 2 y bit +
    4 z bit), per-axis weight factors wf [P, L, 3, 2] (lower, upper corner), their derivatives in x
    dwf [P, L, 3, 2] (unit-cube units, 0 where clamped) and the level switch [L] (1 on, 0 off)."""
    dt, dev = x.dtype, x.device
    meta = meta.to(device=dev, dtype=torch.long)
    res_i, offset, size, hashed = meta.unbind(1)  # [L] each
    res = res_i.to(dt)[None, :, None]  # [1, L, 1]
    u = x[:, None, :] * res  # [P, L, 3]
    inside = (u >= 0) & (u <= res)
    zero = torch.zeros((), dtype=dt, device=dev)
    uc = torch.where(inside, u, torch.where(u > res, res.expand_as(u), zero))  # NaN -> 0, as the kernel
    cell = torch.minimum(torch.floor(uc.detach()), res - 1)
    t = uc - cell  # [P, L, 3]; d t / d u = 1 inside, 0 where clamped (torch.where routes no gradient)
    v = cell.long()[..., None] + torch.arange(2, device=dev)  # [P, L, 3, 2] vertex index per axis and corner bit
    vx, vy, vz = v.unbind(2)  # [P, L, 2] each; corners broadcast as [P, L, z, y, x]
    n = (res_i + 1)[None, :, None]
    dense = vx[:, :, None, None, :] + n[..., None, None] * (vy[:, :, None, :, None] + n[..., None, None] * vz[:, :, :, None, None])
    h = (vx * PRIMES[0])[:, :, None, None, :] ^ (vy * PRIMES[1])[:, :, None, :, None] ^ (vz * PRIMES[2])[:, :, :, None, None]
    h = h & (size - 1)[None, :, None, None, None]
    rows = torch.where(hashed.bool()[None, :, None, None, None], h, dense) + offset[None, :, None, None, None]
    wf = torch.stack([1 - t, t], -1)  # [P, L, 3, 2]
    chain = res * inside.to(dt)  # d u / dx per axis
    dwf = torch.stack([-chain, chain], -1)
    on = (torch.arange(meta.shape[0], device=dev) < active.to(dev).reshape(-1)[0]).to(dt)  # [L]
    return rows.flatten(2), wf, dwf, on


def _corners(fx: torch.Tensor, fy: torch.Tensor, fz: torch.Tensor) -> torch.Tensor:
    """Products fx[c_x] fy[c_y] fz[c_z] of per-axis factors [P, L, 2] over the 8 corners -> [P, L, 8]."""
    return (fz[:, :, :, None, None] * fy[:, :, None, :, None] * fx[:, :, None, None, :]).flatten(2)


def twin_encode(x: torch.Tensor, table: torch.Tensor, meta: torch.Tensor, active: torch.Tensor) -> torch.Tensor:
    """Torch twin of the Warp encoding: features [P, L F] of unit-cube points x [P, 3] (see kernels/hashgrid.py)."""
    rows, wf, _, on = _twin_geometry(x, meta, active)
    P, L = rows.shape[:2]
    w = _corners(*wf.to(table.dtype).unbind(2))  # [P, L, 8]
    feat = torch.einsum("plc,plcf->plf", w, table[rows]) * on.to(table.dtype)[None, :, None]
    return feat.reshape(P, L * table.shape[1])


def twin_gradient(x: torch.Tensor, table: torch.Tensor, g: torch.Tensor, meta: torch.Tensor,
                  active: torch.Tensor) -> torch.Tensor:
    """Torch twin of the Warp spatial-gradient op: sum_j g[:, j] d feat_j / dx -> [P, 3] (unit-cube units)."""
    rows, wf, dwf, on = _twin_geometry(x, meta, active)
    P, L = rows.shape[:2]
    dt = torch.promote_types(table.dtype, g.dtype)
    wf, dwf = wf.to(dt), dwf.to(dt)
    a = torch.einsum("plcf,plf->plc", table[rows].to(dt), g.reshape(P, L, table.shape[1]).to(dt))  # [P, L, 8]
    wx, wy, wz = wf.unbind(2)
    dx, dy, dz = dwf.unbind(2)
    dw = torch.stack([_corners(dx, wy, wz), _corners(wx, dy, wz), _corners(wx, wy, dz)], -1)  # [P, L, 8, 3]
    return torch.einsum("plc,plcd,l->pd", a, dw, on.to(dt))


# ----------------------------------------------------------------------------------------------
# the Warp kernels as torch custom ops (float32; outputs allocated by torch; launches on torch's
# current stream without host synchronisation, so the whole training step can be one CUDA graph)


def _kernels(features: int):
    from slwarp.kernels.hashgrid import hashgrid_kernels

    runtime.init()
    return hashgrid_kernels(int(features))


def _grid(k, x, table, meta, active):
    """The kernels' `Grid` struct (points, table, meta, active) of an op's inputs; k: `_kernels(F)`."""
    return struct(k.Grid, x=x if x.stride(-1) == 1 else x.contiguous(), table=table, meta=meta, active=active)


def _encode_impl(x, table, meta, active):
    P, L, Fe = x.shape[0], meta.shape[0], table.shape[1]
    feat = torch.empty(P, L * Fe, dtype=torch.float32, device=x.device)
    if P > 0:
        k = _kernels(Fe)
        launch(k.encode, (L, P), [_grid(k, x, table, meta, active), desc(feat)], x.device)
    return feat


def _encode_backward_impl(x, table, meta, active, g_feat):
    P, L, Fe = x.shape[0], meta.shape[0], table.shape[1]
    d_table = torch.zeros_like(table)
    if P > 0:
        k = _kernels(Fe)
        launch(k.encode_backward, (L, -(-P // BACKWARD_RUN)), [_grid(k, x, table, meta, active), desc(g_feat),
                                                               BACKWARD_RUN, desc(d_table, Fe)], x.device)
    return d_table


def _gradient_impl(x, table, meta, active, g):
    P, L, Fe = x.shape[0], meta.shape[0], table.shape[1]
    out = torch.zeros(P, 3, dtype=torch.float32, device=x.device)
    if P > 0:
        k = _kernels(Fe)
        launch(k.gradient, (L, P), [_grid(k, x, table, meta, active), desc(g), desc(out, 3)], x.device)
    return out


def _gradient_backward_impl(x, table, meta, active, g, h_out, need_x):
    P, L, Fe = x.shape[0], meta.shape[0], table.shape[1]
    d_table = torch.zeros_like(table)
    d_g = torch.empty(P, L * Fe, dtype=torch.float32, device=x.device)
    d_x = torch.zeros(P, 3, dtype=torch.float32, device=x.device)
    if P > 0:
        k = _kernels(Fe)
        h = h_out if h_out.stride(-1) == 1 else h_out.contiguous()
        launch(k.gradient_backward, (L, P), [_grid(k, x, table, meta, active), desc(g), desc(h, 3), int(need_x),
                                             desc(d_table, Fe), desc(d_g), desc(d_x, 3)], x.device)
    return d_table, d_g, d_x


@torch.library.custom_op("slwarp::hashgrid_encode", mutates_args=())
def _encode_op(x: torch.Tensor, table: torch.Tensor, meta: torch.Tensor, active: torch.Tensor) -> torch.Tensor:
    return _encode_impl(x, table, meta, active)


@_encode_op.register_fake
def _(x, table, meta, active):
    return x.new_empty(x.shape[0], meta.shape[0] * table.shape[1])


@torch.library.custom_op("slwarp::hashgrid_encode_backward", mutates_args=())
def _encode_backward_op(x: torch.Tensor, table: torch.Tensor, meta: torch.Tensor, active: torch.Tensor,
                        g_feat: torch.Tensor) -> torch.Tensor:
    return _encode_backward_impl(x, table, meta, active, g_feat)


@_encode_backward_op.register_fake
def _(x, table, meta, active, g_feat):
    return torch.empty_like(table)


@torch.library.custom_op("slwarp::hashgrid_gradient", mutates_args=())
def _gradient_op(x: torch.Tensor, table: torch.Tensor, meta: torch.Tensor, active: torch.Tensor,
                 g: torch.Tensor) -> torch.Tensor:
    return _gradient_impl(x, table, meta, active, g)


@_gradient_op.register_fake
def _(x, table, meta, active, g):
    return x.new_empty(x.shape[0], 3)


@torch.library.custom_op("slwarp::hashgrid_gradient_backward", mutates_args=())
def _gradient_backward_op(x: torch.Tensor, table: torch.Tensor, meta: torch.Tensor, active: torch.Tensor,
                          g: torch.Tensor, h_out: torch.Tensor, need_x: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    return _gradient_backward_impl(x, table, meta, active, g, h_out, need_x)


@_gradient_backward_op.register_fake
def _(x, table, meta, active, g, h_out, need_x):
    return torch.empty_like(table), g.new_empty(g.shape[0], g.shape[1]), x.new_empty(x.shape[0], 3)


def _encode_setup(ctx, inputs, output):
    x, table, meta, active = inputs
    ctx.save_for_backward(x, table, meta, active)


def _encode_backward(ctx, g_feat):
    x, table, meta, active = ctx.saved_tensors
    d_table = _encode_backward_op(x, table, meta, active, g_feat) if ctx.needs_input_grad[1] else None
    # the encoding's derivative in x contracted with g_feat is exactly the spatial-gradient op
    d_x = _gradient_op(x, table, meta, active, g_feat) if ctx.needs_input_grad[0] else None
    return d_x, d_table, None, None


def _gradient_setup(ctx, inputs, output):
    x, table, meta, active, g = inputs
    ctx.save_for_backward(x, table, meta, active, g)


def _gradient_backward(ctx, h_out):
    x, table, meta, active, g = ctx.saved_tensors
    need_x, need_table, _, _, need_g = ctx.needs_input_grad
    d_table, d_g, d_x = _gradient_backward_op(x, table, meta, active, g, h_out, bool(need_x))
    return d_x if need_x else None, d_table if need_table else None, None, None, d_g if need_g else None


_encode_op.register_autograd(_encode_backward, setup_context=_encode_setup)
_gradient_op.register_autograd(_gradient_backward, setup_context=_gradient_setup)


# Eager calls go through these autograd.Functions, torch.compile through the custom ops above (as render_ops does):
# a custom op's first autograd call imports torch._dynamo, 1.9 s of a fresh `slwarp reconstruct --preset fast` on an
# H100 host (python -X importtime) for a run that compiles nothing. Same kernels, same derivatives.
class _Encode(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, table, meta, active):
        ctx.save_for_backward(x, table, meta, active)
        return _encode_impl(x, table, meta, active)

    @staticmethod
    def backward(ctx, g_feat):
        x, table, meta, active = ctx.saved_tensors
        d_table = _encode_backward_impl(x, table, meta, active, g_feat) if ctx.needs_input_grad[1] else None
        d_x = _Gradient.apply(x, table, meta, active, g_feat) if ctx.needs_input_grad[0] else None
        return d_x, d_table, None, None


class _Gradient(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, table, meta, active, g):
        ctx.save_for_backward(x, table, meta, active, g)
        return _gradient_impl(x, table, meta, active, g)

    @staticmethod
    def backward(ctx, h_out):
        x, table, meta, active, g = ctx.saved_tensors
        need_x, need_table, _, _, need_g = ctx.needs_input_grad
        d_table, d_g, d_x = _gradient_backward_impl(x, table, meta, active, g, h_out, bool(need_x))
        return d_x if need_x else None, d_table if need_table else None, None, None, d_g if need_g else None


def _encode(x, table, meta, active):
    return (_encode_op if torch.compiler.is_compiling() else _Encode.apply)(x, table, meta, active)


def _gradient(x, table, meta, active, g):
    return (_gradient_op if torch.compiler.is_compiling() else _Gradient.apply)(x, table, meta, active, g)


def _check_inputs(x, table, meta, g=None):
    if x.dim() != 2 or x.shape[1] != 3:
        raise ValueError(f"hash grid: points must be [P, 3], got {tuple(x.shape)}")
    if table.dim() != 2:
        raise ValueError(f"hash grid: table must be [E, F], got {tuple(table.shape)}")
    if meta.dim() != 2 or meta.shape[1] != 4:
        raise ValueError(f"hash grid: meta must be [L, 4] (res, offset, size, hashed), got {tuple(meta.shape)}")
    if g is not None and tuple(g.shape) != (x.shape[0], meta.shape[0] * table.shape[1]):
        raise ValueError(f"hash grid: cotangent g must be [P, L F] = {(x.shape[0], meta.shape[0] * table.shape[1])}, "
                         f"got {tuple(g.shape)}")


def hashgrid_encode(x: torch.Tensor, table: torch.Tensor, meta: torch.Tensor, active: torch.Tensor, *,
                    backend: str = "warp") -> torch.Tensor:
    """Trilinear hash-grid features [P, L F] of unit-cube points x [P, 3] (see kernels/hashgrid.py).

    table [E, F]; meta [L, 4] int32 from `HashGridLayout.meta`; active: int32 [1], the number of levels
    switched on (a device tensor, so that changing it needs no recompilation or graph recapture).
    Differentiable in table and x (the x derivative is `hashgrid_gradient`); backend "warp" computes in
    float32, "torch" in the inputs' dtype.
    """
    check_backend(backend)
    _check_inputs(x, table, meta)
    if backend == "torch":
        return twin_encode(x, table, meta, active)
    return _encode(x.to(torch.float32), table.to(torch.float32), meta.to(torch.int32), active.to(torch.int32))


def hashgrid_gradient(x: torch.Tensor, table: torch.Tensor, g: torch.Tensor, meta: torch.Tensor, active: torch.Tensor,
                      *, backend: str = "warp") -> torch.Tensor:
    """sum_j g[:, j] d feat_j / dx [P, 3] (unit-cube units): the encoding's Jacobian [P, L F, 3] contracted
    with a cotangent g [P, L F] without materialising it. Differentiable (first order) in table, g and x."""
    check_backend(backend)
    _check_inputs(x, table, meta, g)
    if backend == "torch":
        return twin_gradient(x, table, g, meta, active)
    return _gradient(x.to(torch.float32), table.to(torch.float32), meta.to(torch.int32), active.to(torch.int32),
                     g.to(torch.float32))
