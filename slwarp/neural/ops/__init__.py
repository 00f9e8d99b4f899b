"""Torch-facing ops: the Warp kernels wrapped as torch custom ops, with a pure-torch twin each.

Public functions take `backend="warp"` (default: fused Warp kernels, CPU or CUDA, float32) or
`backend="torch"` (the twin in `twin`: any dtype, differentiable by autograd).

    render_structured_light(...)  the fused renderer (differentiable in sdf, sdf_grad and inv_s)
    camera_rays(...)              pixels -> rays and near/far distances
    stratified_samples(...)       stratified samples with per-ray jitter
    upsample_samples(...)         one NeuS hierarchical up-sampling step
    merge_samples(...)            merge two sorted per-ray sample lists
    reproject_patterns(...)       bilinear values of K patterns at projector pixels (differentiable in both)

- `render_ops`: the fused render (one forward and one hand-written backward, kernels/render.py) as a
  torch.autograd.Function and, under torch.compile, as torch.library custom ops that stay opaque (no graph break).
- `sampling_ops`: rays and samples (no gradients flow through them; kernels/sampling.py).
- `pattern_ops`: pattern reprojection for pattern design (kernels/reproject.py: the backward scatters into the
  patterns with atomics) as a torch.autograd.Function.
- `hashgrid_ops`: the multiresolution hash-grid encoding and its spatial gradient (kernels/hashgrid.py), which the
  hash-grid field imports.
- `twin`: the pure-torch twins, named after the ops they mirror.
- `launch`: what the ops share: the backends, the working volume's bounds as kernels take them, and Warp launches
  from torch tensors.
"""
from .launch import BACKENDS
from .pattern_ops import reproject_patterns
from .render_ops import RenderInputs, RenderOutput, pack_patterns, pack_projector, render_structured_light
from .sampling_ops import camera_rays, merge_samples, stratified_samples, upsample_samples

__all__ = [
    "BACKENDS",
    "RenderInputs",
    "RenderOutput",
    "render_structured_light",
    "camera_rays",
    "stratified_samples",
    "upsample_samples",
    "merge_samples",
    "reproject_patterns",
    "pack_projector",
    "pack_patterns",
]
