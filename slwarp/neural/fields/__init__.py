"""The SDF fields, in millimetres: a field maps points x [..., 3] (camera frame, mm) to signed distances [...] (mm).

- `volume`: the working volume (`Volume`) a field is normalised to.
- `mlp`: NeuS's network (`NeuSField`, field.kind "mlp") and NeuS's learned variance (`LearnedVariance`).
- `hashgrid`: the multiresolution hash-grid field (`HashGridSDF`, field.kind "hashgrid"); its encoding ops are in
  slwarp.neural.ops.hashgrid_ops.
- here: `make_field`, the one place a field config becomes a network, and `sdf_and_gradient`, a field's value and
  gradient whatever the module.
"""
from __future__ import annotations

import math

import torch
import torch.nn as nn

from .hashgrid import HashGridLayout, HashGridSDF
from .mlp import LearnedVariance, NeuSField
from .volume import Volume, register_volume_buffers

__all__ = ["Volume", "register_volume_buffers", "NeuSField", "LearnedVariance", "HashGridSDF", "HashGridLayout",
           "make_field", "auto_finest_resolution", "sdf_and_gradient"]


def auto_finest_resolution(volume: Volume, pixel_mm: float) -> int:
    """Cells per side of a hash grid's finest level that match a pixel footprint `pixel_mm` (mm, at the working
    depth): the power of two nearest (in log scale) to the volume's largest side over it. 2048 (0.39 mm cells)
    on the default rig, 512 (1.5 mm) on the small one; finer cells failed on the small rig (docs/hashgrid.md)."""
    if not pixel_mm > 0:
        raise ValueError(f"auto_finest_resolution: the pixel footprint must be > 0 mm, got {pixel_mm}")
    cells = 2.0 * volume.scale / pixel_mm
    return int(2 ** min(20, max(0, round(math.log2(max(cells, 1.0))))))


def make_field(config, volume: Volume, *, init: str = "sphere", far: float | None = None,
               pixel_mm: float | None = None) -> nn.Module:
    """The SDF network a TrainConfig.field section describes, sized to the working volume (mm in, mm out).
    init and far as NeuSField takes them; pixel_mm: the camera's pixel footprint (mm) at the working depth,
    needed by a hash grid with grid_finest "auto". The one place that turns a field config into a network: a
    new kind of field is added here (and its options in slwarp.neural.config.FieldConfig)."""
    if config.kind == "mlp":
        return NeuSField(volume, hidden=config.hidden, layers=config.layers, skip=config.skip, n_freqs=config.n_freqs,
                         init=init, far=far)
    if config.kind != "hashgrid":
        raise ValueError(f"make_field: unknown field kind {config.kind!r} (mlp or hashgrid)")
    finest = config.grid_finest
    if finest == "auto":
        if pixel_mm is None:
            raise ValueError("make_field: grid_finest 'auto' needs the pixel footprint pixel_mm (mm)")
        finest = max(config.grid_base, auto_finest_resolution(volume, pixel_mm))
    return HashGridSDF(volume, levels=config.grid_levels, log2_table_size=config.grid_log2_table,
                       base_resolution=config.grid_base, finest_resolution=finest, hidden=config.grid_hidden,
                       layers=config.grid_layers, activation=config.grid_activation, gradient=config.grid_gradient,
                       init=init, far=far, active_levels=config.grid_start_levels)


def sdf_and_gradient(field: nn.Module, x: torch.Tensor, create_graph: bool = True):
    """f(x) [...] and grad f(x) [..., 3], differentiable, for any torch SDF module: its own
    `value_and_gradient` when it has one (explicit, first-order), else autograd with a double backward."""
    explicit = getattr(field, "value_and_gradient", None)
    if explicit is not None:
        return explicit(x.detach())
    with torch.enable_grad():
        x = x.detach().requires_grad_(True)
        f = field(x)
        (g,) = torch.autograd.grad(f, x, torch.ones_like(f), create_graph=create_graph)
    return f, g
