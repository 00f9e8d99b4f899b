"""The fused structured-light render as a torch op (`render_structured_light`, differentiable in sdf, sdf_grad and
inv_s), with `backend="warp"` (default: fused Warp kernels, CPU or CUDA, float32) or `backend="torch"` (the twin in
slwarp.neural.ops.twin: any dtype, differentiable by autograd); importable from slwarp.neural.ops.

The Warp render composes with autograd through one forward and one hand-written backward (kernels/render.py),
reached eagerly through a torch.autograd.Function and, under torch.compile, through torch.library custom ops
(+ register_fake, register_autograd) that stay opaque (no graph break).
"""
from __future__ import annotations

import typing
from typing import NamedTuple

import torch

from . import twin
from .launch import bounds_list, check_backend, desc, f32, f32v, launch, projector_struct, struct, vec3
from ...scans.scanner import PackedProjector
from slwarp.kernels.render import (Cotangents, ForwardOutputs, ForwardSaved, InputGrads, RaySamples, RenderParams,
                                   render_kernels)

__all__ = [
    "RenderOutput",
    "render_structured_light",
    "pack_projector",
    "pack_patterns",
]


class RenderOutput(NamedTuple):
    """Result of `render_structured_light` (R rays, S samples, N patterns).

    rendered [R, N]: volume-rendered intensities sum_k w_k (a + b P_n(pi(x_k)));
    surface_points [R, 3]: expected surface point sum_k w_k x_k / (sum_k w_k + 1e-6) (camera frame, mm; the
    literal sum_k w_k x_k for an opaque ray, normalised so that missing opacity does not pull it toward the
    camera);
    surface_rendered [R, N]: a + b P_n(pi(surface point));
    weights [R, S]: NeuS weights; depth [R]: camera-frame z of the surface point (mm);
    eikonal [R, S]: (|grad f| - 1)^2 inside the working volume, 0 outside;
    weight_sum [R]: sum_k w_k (opacity of the ray); eikonal_sum [R]: sum_k eikonal (differentiable: a
    loss on it moves one number per ray instead of S); eikonal_count [R]: samples inside the volume.
    """

    rendered: torch.Tensor
    surface_points: torch.Tensor
    surface_rendered: torch.Tensor
    weights: torch.Tensor
    depth: torch.Tensor
    eikonal: torch.Tensor
    weight_sum: torch.Tensor
    eikonal_sum: torch.Tensor
    eikonal_count: torch.Tensor


def pack_projector(projector) -> PackedProjector:
    """The 24 packed floats (`slwarp.scans.scanner.PackedProjector`) of a `slwarp.Projector`, of a
    PackedProjector, or of any sequence of 24 numbers in that order."""
    if isinstance(projector, PackedProjector):
        return projector
    if isinstance(projector, (list, tuple)):
        if len(projector) != len(PackedProjector._fields):
            raise ValueError(f"a packed projector has {len(PackedProjector._fields)} floats, got {len(projector)}")
        return PackedProjector(*(float(x) for x in projector))
    return projector.packed


def pack_patterns(patterns: torch.Tensor) -> torch.Tensor:
    """[N, H, W] -> contiguous float32 [H, W, N]: the N values of a projector pixel side by side."""
    return patterns.detach().to(torch.float32).permute(1, 2, 0).contiguous()


# ----------------------------------------------------------------------------------------------
# the render's Warp launches: the kernels take their arguments as structs (kernels/render.py), filled by field
# name from the NamedTuples below in one place (`_render_structs`, `_fill`)


def _empty_like_layout(ref: torch.Tensor, *tail: int) -> torch.Tensor:
    """An [R, S, *tail] float32 tensor in the memory order of ref [R, S] (sample-major if ref is)."""
    R, S = ref.shape
    if R > 1 and ref.stride(0) == 1:
        return torch.empty(S, R, *tail, dtype=torch.float32, device=ref.device).transpose(0, 1)
    return torch.empty(R, S, *tail, dtype=torch.float32, device=ref.device)


class RenderInputs(NamedTuple):
    """The fused render's inputs as the Warp kernels take them (R rays, S samples, N patterns): float32
    tensors sdf [R, S], sdf_grad [R, S, 3], z_vals [R, S], rays_o [R, 3], rays_d [R, 3], a [R], b [R],
    patterns_hwn [H, W, N] and inv_s [1]; the projector's 24 packed floats; NeuS's cos-anneal ratio; the last
    sample's interval (< 0: the previous interval); bounds [xmin, ymin, zmin, xmax, ymax, zmax] (mm).
    The torch twin takes the same list with patterns [N, H, W] (twin.render_structured_light)."""

    sdf: torch.Tensor
    sdf_grad: torch.Tensor
    z_vals: torch.Tensor
    rays_o: torch.Tensor
    rays_d: torch.Tensor
    a: torch.Tensor
    b: torch.Tensor
    patterns_hwn: torch.Tensor
    projector: list
    inv_s: torch.Tensor
    cos_anneal_ratio: float
    last_delta: float
    bounds: list


class _KernelOutputs(NamedTuple):
    """What the forward kernels write: the RenderOutput's tensors plus T_k (trans [R, S]) and the patterns' values
    at the samples (pattern_values [R, S, N]), kept for the backward. The order is the custom op's."""

    weights: torch.Tensor
    rendered: torch.Tensor
    surface: torch.Tensor
    surface_rendered: torch.Tensor
    depth: torch.Tensor
    weight_sum: torch.Tensor
    eikonal: torch.Tensor
    eikonal_sum: torch.Tensor
    eikonal_count: torch.Tensor
    trans: torch.Tensor
    pattern_values: torch.Tensor


class _Saved(NamedTuple):
    """The forward's outputs the backward reads (see _KernelOutputs)."""

    trans: torch.Tensor
    surface: torch.Tensor
    weight_sum: torch.Tensor
    pattern_values: torch.Tensor


class _Cotangents(NamedTuple):
    """Float32 cotangents of the outputs (R rays, S samples, N patterns): those of weights [R, S] and eikonal
    [R, S] may be None (no loss used them: the kernel skips them), the others are tensors (zeros where missing)."""

    g_weights: typing.Optional[torch.Tensor]
    g_rendered: torch.Tensor
    g_surface: torch.Tensor
    g_surface_rendered: torch.Tensor
    g_depth: torch.Tensor
    g_weight_sum: torch.Tensor
    g_eikonal: typing.Optional[torch.Tensor]
    g_eikonal_sum: torch.Tensor


# the inputs autograd saves as tensors (the others are constants)
_SAVED_INPUTS = ("sdf", "sdf_grad", "z_vals", "rays_o", "rays_d", "a", "b", "patterns_hwn", "inv_s")


def _fill(cls, values, **more):
    """Warp struct `cls` with its fields from the same-named fields of the NamedTuple `values`, or from `more`."""
    return struct(cls, **{k: getattr(values, k) for k in cls.vars if k not in more}, **more)


def _render_structs(inp: RenderInputs) -> tuple:
    """(RaySamples, RenderParams): the structs every render kernel takes, made once per forward (the eager
    backward reuses them: its inputs are the same tensors)."""
    bnd = inp.bounds
    params = struct(RenderParams, patterns=inp.patterns_hwn, projector=projector_struct(inp.projector), inv_s=inp.inv_s,
                    cos_anneal_ratio=float(inp.cos_anneal_ratio), last_delta=float(inp.last_delta),
                    bmin=vec3(bnd[0:3]), bmax=vec3(bnd[3:6]))
    return _fill(RaySamples, inp), params


def _cotangent_struct(cots: _Cotangents):
    return _fill(Cotangents, cots, has_g_weights=int(cots.g_weights is not None),
                 has_g_eikonal=int(cots.g_eikonal is not None))


def _render_forward_impl(inp: RenderInputs, structs: tuple | None = None) -> _KernelOutputs:
    """The forward kernels on RenderInputs; structs: `_render_structs(inp)` when already made."""
    R, S = inp.z_vals.shape
    N = inp.patterns_hwn.shape[2]
    dev = inp.z_vals.device
    opts = dict(dtype=torch.float32, device=dev)
    out = _KernelOutputs(
        weights=_empty_like_layout(inp.z_vals), rendered=torch.empty(R, N, **opts), surface=torch.empty(R, 3, **opts),
        surface_rendered=torch.empty(R, N, **opts), depth=torch.empty(R, **opts), weight_sum=torch.empty(R, **opts),
        eikonal=_empty_like_layout(inp.z_vals), eikonal_sum=torch.empty(R, **opts), eikonal_count=torch.empty(R, **opts),
        trans=_empty_like_layout(inp.z_vals), pattern_values=_empty_like_layout(inp.z_vals, N))
    if R > 0:
        samples, forward, _ = render_kernels(int(N))
        rays, params = structs or _render_structs(inp)
        values = desc(out.pattern_values, N)
        launch(samples, (R, S), [rays, params, values], dev)
        launch(forward, R, [rays, params, values, _fill(ForwardOutputs, out)], dev)
    return out


def _render_backward_impl(inp: RenderInputs, saved: _Saved, cots: _Cotangents, structs: tuple | None = None):
    """(d sdf [R, S], d sdf_grad [R, S, 3], d inv_s [1]) from the cotangents of the outputs (see `_cotangents`)
    and what the forward saved; structs: `_render_structs(inp)` when already made."""
    R, S = inp.z_vals.shape
    dev = inp.z_vals.device
    d_sdf = _empty_like_layout(inp.sdf)
    d_grad = _empty_like_layout(inp.sdf, 3)
    d_inv_s = torch.empty(R, dtype=torch.float32, device=dev)
    if R > 0:
        N = int(inp.patterns_hwn.shape[2])
        _, _, backward = render_kernels(N)
        rays, params = structs or _render_structs(inp)
        launch(backward, R, [rays, params, desc(saved.pattern_values, N), _fill(ForwardSaved, saved),
                             _cotangent_struct(cots), struct(InputGrads, d_sdf=d_sdf, d_grad=d_grad, d_inv_s=d_inv_s)], dev)
    return d_sdf, d_grad, d_inv_s.sum().reshape(1)


def _cotangents(z_vals, N, grads) -> _Cotangents:
    """The float32 `_Cotangents` of (weights, rendered, surface, surface_rendered, depth, weight_sum, eikonal,
    eikonal_sum): None for weights/Eikonal stays None, other missing ones become zeros (they are [R] or [R, N]:
    cheap)."""
    g_weights, g_rendered, g_surface, g_srend, g_depth, g_wsum, g_eik, g_eik_sum = grads
    R, S = z_vals.shape

    def cot(g, *shape):
        if g is None:
            return z_vals.new_zeros(shape, dtype=torch.float32)
        return f32v(g) if shape[-1] == 3 and len(shape) == 2 and shape[0] == R else f32(g)

    return _Cotangents(f32(g_weights) if g_weights is not None else None, cot(g_rendered, R, N), cot(g_surface, R, 3),
                       cot(g_srend, R, N), cot(g_depth, R), cot(g_wsum, R), f32(g_eik) if g_eik is not None else None,
                       cot(g_eik_sum, R))


# ----------------------------------------------------------------------------------------------
# autograd: one saving step and one backward, shared by the eager path (_RenderFunction: lighter than a
# custom op's dispatch, measured ~0.4 ms less per forward + backward on the CPU) and the torch.compile path
# (the custom ops below, opaque to the compiler).


def _save_for_backward(ctx, inputs, outputs, opaque: bool, structs: tuple | None = None) -> None:
    inp, out = RenderInputs(*inputs), _KernelOutputs(*outputs)
    ctx.save_for_backward(*(getattr(inp, k) for k in _SAVED_INPUTS), *(getattr(out, k) for k in _Saved._fields))
    ctx.constants = inp._replace(**{k: None for k in _SAVED_INPUTS})
    ctx.opaque = opaque  # backward through the custom op (compiled graphs) or the launch itself (eager)
    # the forward's kernel structs, for the eager backward: they point at these inputs' memory
    ctx.structs = structs
    ctx.pointers = [getattr(inp, k).data_ptr() for k in _SAVED_INPUTS] if structs is not None else None


def _backward(ctx, *grads):
    saved = ctx.saved_tensors
    n = len(_SAVED_INPUTS)
    inp = ctx.constants._replace(**{k: t.detach() for k, t in zip(_SAVED_INPUTS, saved[:n])})
    kept = _Saved(*(t.detach() for t in saved[n:]))
    cots = _cotangents(inp.z_vals, inp.patterns_hwn.shape[2], grads[:8])
    if ctx.opaque:
        d_sdf, d_grad, d_inv_s = _render_backward(*inp, *kept, *cots)
    else:
        # reuse the forward's structs unless saved-tensor hooks gave back copies (other memory)
        same = ctx.pointers == [t.data_ptr() for t in saved[:n]]
        d_sdf, d_grad, d_inv_s = _render_backward_impl(inp, kept, cots, ctx.structs if same else None)
    grads_in = dict(sdf=d_sdf, sdf_grad=d_grad, inv_s=d_inv_s)  # the differentiable inputs
    return tuple(grads_in.get(k) for k in RenderInputs._fields)


class _RenderFunction(torch.autograd.Function):
    """The eager-mode autograd wrapper of the fused render."""

    @staticmethod
    def forward(ctx, *inputs):
        inp = RenderInputs(*inputs)
        structs = _render_structs(inp) if inp.z_vals.shape[0] > 0 else None
        out = _render_forward_impl(inp, structs)
        _save_for_backward(ctx, inputs, out, opaque=False, structs=structs)
        ctx.mark_non_differentiable(out.eikonal_count, out.trans, out.pattern_values)
        return tuple(out)

    backward = staticmethod(_backward)


# The custom ops' schemas are written from the NamedTuples' fields (the one list of the render's arguments)
_SCHEMA_TYPES = {torch.Tensor: "Tensor", typing.Optional[torch.Tensor]: "Tensor?", list: "float[]", float: "float"}


def _schema(*records, returns: int) -> str:
    """A custom op's schema: the fields of the NamedTuples `records` in order, then `returns` tensors."""
    hints = [(k, t) for r in records for k, t in typing.get_type_hints(r).items()]
    args = ", ".join(f"{_SCHEMA_TYPES[t]} {k}" for k, t in hints)
    return f"({args}) -> ({', '.join(['Tensor'] * returns)})"


def _render_forward_op(*inputs):
    """RenderInputs -> _KernelOutputs."""
    return tuple(_render_forward_impl(RenderInputs(*inputs)))


def _render_backward_op(*args):
    """`_render_backward_impl` on RenderInputs, then _Saved and _Cotangents."""
    n, m = len(RenderInputs._fields), len(_Saved._fields)
    return _render_backward_impl(RenderInputs(*args[:n]), _Saved(*args[n:n + m]), _Cotangents(*args[n + m:]))


_render_forward = torch.library.custom_op("slwarp::render_forward", _render_forward_op, mutates_args=(),
                                          schema=_schema(RenderInputs, returns=len(_KernelOutputs._fields)))
_render_backward = torch.library.custom_op("slwarp::render_backward", _render_backward_op, mutates_args=(),
                                           schema=_schema(RenderInputs, _Saved, _Cotangents, returns=3))


@_render_forward.register_fake
def _(*inputs):
    inp = RenderInputs(*inputs)
    R, S = inp.z_vals.shape
    N = inp.patterns_hwn.shape[2]
    e = lambda *shape: inp.z_vals.new_empty(shape, dtype=torch.float32)  # noqa: E731
    return tuple(_KernelOutputs(weights=e(R, S), rendered=e(R, N), surface=e(R, 3), surface_rendered=e(R, N), depth=e(R),
                                weight_sum=e(R), eikonal=e(R, S), eikonal_sum=e(R), eikonal_count=e(R), trans=e(R, S),
                                pattern_values=e(R, S, N)))


@_render_backward.register_fake
def _(sdf, sdf_grad, z_vals, *args):
    R, S = z_vals.shape
    return z_vals.new_empty(R, S), z_vals.new_empty(R, S, 3), z_vals.new_empty(1)


_render_forward.register_autograd(_backward, setup_context=lambda ctx, inputs, output: _save_for_backward(
    ctx, inputs, output, opaque=True))


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
    check_backend(backend)
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
    bnd = bounds_list(bounds)
    ld = -1.0 if last_delta is None else float(last_delta)
    if not isinstance(inv_s, torch.Tensor):
        inv_s = torch.tensor(float(inv_s), device=z_vals.device)
    if backend == "torch":
        pat_nhw = patterns if patterns_layout == "NHW" else patterns.permute(2, 0, 1)
        out = _KernelOutputs(*twin.render_structured_light(sdf, sdf_grad, z_vals, rays_o, rays_d, a, b, pat_nhw, proj, inv_s,
                                                           float(cos_anneal_ratio), ld, bnd), trans=None,
                             pattern_values=None)
    else:
        pat_hwn = pack_patterns(patterns) if patterns_layout == "NHW" else patterns.detach().to(torch.float32).contiguous()
        sg = sdf_grad.to(torch.float32)
        inputs = RenderInputs(sdf.to(torch.float32), sg if sg.stride(-1) == 1 else sg.contiguous(), f32(z_vals),
                              f32v(rays_o), f32v(rays_d), f32(a), f32(b), pat_hwn, list(proj),
                              inv_s.to(torch.float32).reshape(1), float(cos_anneal_ratio), ld, bnd)
        outs = _render_forward(*inputs) if torch.compiler.is_compiling() else _RenderFunction.apply(*inputs)
        out = _KernelOutputs(*outs)
    return RenderOutput(out.rendered, out.surface, out.surface_rendered, out.weights, out.depth, out.eikonal,
                        out.weight_sum, out.eikonal_sum, out.eikonal_count)
