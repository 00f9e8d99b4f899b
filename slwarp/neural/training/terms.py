"""The training loss: the renderer's losses weighted by the schedule (`step_loss`), and the terms that use the
depth-search map (`MapTerms`).

    terms = MapTerms(field, config.init, volume.scale, device, camera, depth_range, backend)
    terms.init_depth, terms.surface_depth = ...      # [H*W] mm (NaN: none): slwarp.neural.start
    loss = step_loss(losses, batch, weights, config.schedule, terms, compile=renderer.compile_field)

The map terms, per batch pixel: in the warm-up the rendered depth and full opacity are pulled onto the starting map;
the surface term (init.surface_weight in the warm-up, init.surface_after after it: `surface_term_weights`) puts the
field's zero level at the map's confirmed depths; the free-space term (init.free_space, after the warm-up:
`free_space_weights`) pushes the samples before such a depth out of the solid where the field shows a surface in
front of it. On CUDA with runtime.compile they run torch.compile'd as one graph (`MapTerms.compiled`), which reads
the working volume's scale as a tensor (`scale_mm`), so one process compiles it once for every scan of the same sizes.
"""
from __future__ import annotations

import torch

from .. import ops
from ..render import compile_in_process

__all__ = ["MISSED_MM", "surface_term_weights", "free_space_weights", "MapTerms", "step_loss"]

MISSED_MM = 5.0  # after the warm-up, the surface term acts where the field's depth is this far behind the map's
# (and the free-space term where it is this far in front, on the samples this far before the map's point)


def _off_the_map(target: torch.Tensor, rendered: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(has target, field behind, field in front) [R] bool: where the rendered depth [R] (mm) lies more than MISSED_MM
    behind or in front of the map's confirmed depth target [R] (mm, NaN: none)."""
    ok = torch.isfinite(target)
    target = torch.nan_to_num(target)
    return ok, ok & (target < rendered - MISSED_MM), ok & (target > rendered + MISSED_MM)


def surface_term_weights(target: torch.Tensor, rendered: torch.Tensor, warm, during: float, after: float,
                         in_front: bool = False) -> torch.Tensor:
    """Per-pixel weights [R] of the surface term (MapTerms.surface_term): `during` on every pixel with a target
    in the warm-up (warm 1), and after it (warm 0) `after` only where the rendered depth [R] (mm) lies more than
    MISSED_MM behind the target [R] (mm, NaN: none): a thin part in front that the field lost; with `in_front` also
    where it lies more than MISSED_MM in front of the target (the field carried a surface over the pixel's own, e.g.
    a step's edge over the lower step). Elsewhere the photometric loss alone decides. warm: a float or a 0-d tensor
    in [0, 1]."""
    ok, behind, ahead = _off_the_map(target, rendered)
    missed = behind | ahead if in_front else behind
    return ok.to(rendered.dtype) * (warm * during) + missed.to(rendered.dtype) * ((1.0 - warm) * after)


def free_space_weights(target: torch.Tensor, rendered: torch.Tensor, warm, after: float) -> torch.Tensor:
    """Per-pixel weights [R] of the free-space term (MapTerms.free_space_term): `after` (outside the warm-up: warm 0)
    where the rendered depth [R] (mm) lies more than MISSED_MM in front of the map's confirmed depth target [R]
    (mm, NaN: none), else 0. The pixel's own codes put its surface at the target, so the field's surface in front of
    it is one the field bridged across a gap or grew over the background (steps, boxes: docs/accuracy.md)."""
    _, _, bridged = _off_the_map(target, rendered)
    return bridged.to(rendered.dtype) * ((1.0 - warm) * after)


class MapTerms:
    """The loss terms that use the depth-search map, and the maps they use.

    field: the SDF module (x [..., 3] mm -> [...] mm); init: the config's InitConfig; scale: the working volume's
    scale (mm, the terms' unit); camera, depth_range (near, far) mm and backend: how a batch's rays are made.
    init_depth [H*W] (mm, NaN: none, or None): the starting map the warm-up pulls onto; surface_depth [H*W] (mm, NaN:
    none, or None: the surface and free-space terms off): its depths that the pixels' own codes confirm.
    A plain object, not a module: torch.compile reads its attributes as inputs, so the graph compiled for one scan
    serves the next."""

    def __init__(self, field: torch.nn.Module, init, scale: float, device, camera, depth_range, backend: str):
        self.field, self.init = field, init
        self.camera, self.depth_range, self.backend = camera, depth_range, backend
        # the terms' unit (mm), a device tensor: an input of their compiled graph, which so serves every scan of the
        # same sizes (fields.register_volume_buffers)
        self.scale_mm = torch.tensor(scale, dtype=torch.float32, device=device)
        self.init_depth: torch.Tensor | None = None
        self.surface_depth: torch.Tensor | None = None
        self._compiled = None  # `loss`, compiled on first use (see `compiled`)

    def acts(self, warm) -> bool:
        """Whether the terms add to this step's loss (warm: a float, or a 0-d tensor: then they always do)."""
        return self.init_depth is not None and (torch.is_tensor(warm) or warm != 0.0 or self.init.surface_after > 0
                                                or self.init.free_space > 0)

    def on_batch(self, batch, losses, warm, compile: bool) -> torch.Tensor:
        """The terms (0-d, dimensionless) on a pixel batch (render.PixelBatch) and its render's losses
        (render.RenderLosses); compile: run them compiled (fixed at the first call: `compiled`)."""
        _, d, _, _ = ops.camera_rays(batch.uv, self.camera, self.depth_range, backend=self.backend)
        return self.compiled(compile)(d, batch.index, losses.output.depth, losses.output.weight_sum, losses.z_vals,
                                      losses.sdf, warm)

    def compiled(self, compile: bool):
        """`loss`, torch.compile'd when `compile` (the renderer compiles its field: CUDA with runtime.compile) at the
        first call, which decides for good: the terms are some 90 small element-wise kernels and one more field
        evaluation, which compiling fuses (on an H100 `fast`'s step took 1.93 ms with them,
        bench/results/train-speed-cuda-fast-17a.md, and 1.61 ms timed without them, -fast-e2e-16c.md; compiled, with
        the sampling kernels parallel over samples, 1.63 ms: -fast-17b.md). Compiled, the weights come as 0-d tensors
        in every step (`step_loss`), so that one compiled graph serves the plain steps before the capture and the
        captured one."""
        fn = self._compiled
        if fn is None:
            fn = compile_in_process(self.loss) if compile else self.loss
            self._compiled = fn
        return fn

    def loss(self, d: torch.Tensor, index: torch.Tensor, depth: torch.Tensor, weight_sum: torch.Tensor,
             z_vals: torch.Tensor, sdf: torch.Tensor, warm) -> torch.Tensor:
        """The terms (dimensionless), for a batch of R pixels: unit ray directions d [R, 3], flat pixel indices [R],
        the rendered depth [R] (mm) and opacity [R], the samples' distances z_vals [R, S] (mm) and SDF [R, S] (mm,
        differentiable). In the warm-up (warm 1) the rendered depth and full opacity are pulled onto the map; the
        surface term (`surface_term`) and the free-space term (`free_space_term`) act at the confirmed depths.
        warm: a float, or a 0-d tensor (then every term is computed, weighted)."""
        init = self.init
        captured = torch.is_tensor(warm)
        target = self.init_depth[index]
        ok = torch.isfinite(target).to(target.dtype)
        n = ok.sum().clamp(min=1.0)
        loss = torch.zeros((), device=depth.device)
        if captured or warm != 0.0:
            # warm-up: pull the rendered depth (and full opacity) onto the initial depth map
            depth_err = ((depth - torch.nan_to_num(target)).abs() * ok).sum() / n
            opacity = ((1.0 - weight_sum).abs() * ok).sum() / n
            loss = loss + warm * (depth_err / self.scale_mm + opacity)
        if self.surface_depth is not None:
            surface = self.surface_depth[index]
            t = torch.nan_to_num(surface) / d[:, 2]  # distance along the unit ray to camera depth surface
            per_pixel = surface_term_weights(surface, depth.detach(), warm, init.surface_weight, init.surface_after,
                                             init.surface_in_front)
            loss = loss + self.surface_term(d, t, per_pixel, n)
            if init.free_space > 0:
                bridged = free_space_weights(surface, depth.detach(), warm, init.free_space)
                loss = loss + self.free_space_term(t, bridged, z_vals, sdf, n)
        return loss

    def surface_term(self, d: torch.Tensor, t: torch.Tensor, weight: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
        """The SDF term at the initial map's points (dimensionless: mm over the volume's scale), summed over the
        batch's pixels with per-pixel weights [R] (0 where no target) over n: |f(p)| at the point p at distance t [R]
        (mm) along each pixel's unit ray d [R, 3], plus relu(-f) at band mm before it and relu(f) at band mm
        behind it along the ray. The rendered depth's gradient reaches the SDF only through NeuS weights near
        the field's current surface, so it cannot raise a surface far in front of it (a 2.5 mm rod 100 mm in
        front of the background: bench/thin_stages.py); this term acts on the field at the point itself."""
        band = self.init.surface_band_mm
        along = torch.stack([t - band, t, t + band])  # [3, R]
        f = self.field(along[..., None] * d[None])  # [3, R] mm
        term = f[1].abs() + torch.relu(-f[0]) + torch.relu(f[2])
        return (term * weight).sum() / n / self.scale_mm

    def free_space_term(self, t: torch.Tensor, weight: torch.Tensor, z_vals: torch.Tensor, sdf: torch.Tensor,
                        n: torch.Tensor) -> torch.Tensor:
        """The free-space term (dimensionless: mm over the volume's scale), summed over the batch's pixels with
        per-pixel weights [R] (0 where none) over n: the sum of relu(-f) over the ray's samples (z_vals [R, S] along
        the unit ray, sdf [R, S] mm, differentiable) more than MISSED_MM in front of the map's point at distance t [R]
        (mm) along the ray. The pixel sees its surface there, so the ray is empty before it; the samples
        there are the ones NeuS's up-sampling put on the field's wrong surface, so the term acts where that
        surface is, at no extra field evaluation."""
        before = (z_vals < (t - MISSED_MM)[:, None]).to(sdf.dtype)
        per_ray = (torch.relu(-sdf) * before).sum(1)
        return (per_ray * weight).sum() / n / self.scale_mm


def step_loss(losses, batch, weights: dict, schedule, terms: MapTerms, compile: bool) -> torch.Tensor:
    """The step's loss (0-d): lambda_reg x Eikonal, the map terms where they act, and outside the warm-up the
    photometric losses (lambda_rc x rendered colour + lambda_sc x surface colour). losses: the renderer's
    RenderLosses of the pixel batch `batch`; weights "warmup" (1 in the depth-search warm-up, else 0) and
    "lambda_sc": floats, or 0-d device tensors (a captured graph's: then every term is computed, weighted);
    schedule: a ScheduleConfig; compile: run the map terms compiled (`MapTerms.compiled`)."""
    warm, w_sc = weights["warmup"], weights["lambda_sc"]
    captured = torch.is_tensor(warm)
    loss = schedule.lambda_reg * losses.eikonal
    if terms.acts(warm):
        loss = loss + terms.on_batch(batch, losses, warm, compile)
    if captured or warm != 1.0:
        photometric = schedule.lambda_rc * losses.color
        if captured or w_sc != 0.0:
            photometric = photometric + w_sc * losses.surface
        loss = loss + (1.0 - warm) * photometric
    return loss
