"""SDF networks and the learned NeuS variance, in millimetres.

The renderer works in the camera frame in mm, so a field maps points x [..., 3] (mm) to signed distances
[...] (mm). `NeuSField` keeps NeuS's network in a normalised space: the working volume (an axis-aligned
box in the camera frame, from the scan's valid pixels between the near and far depth) is mapped into
[-1, 1]^3 by x_n = (x - center) / scale with scale = half the box's largest side, and
f(x) = scale * mlp(x_n): distances and gradients stay metric (|grad f| = 1 for a true SDF).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
from torch.nn.utils import parametrizations


@dataclass(frozen=True)
class Volume:
    """Axis-aligned working volume in the camera frame (mm): lo [3], hi [3]."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]

    @property
    def center(self) -> np.ndarray:
        return (np.asarray(self.lo) + np.asarray(self.hi)) / 2

    @property
    def scale(self) -> float:
        """Half the largest side (mm): the box fits in [-1, 1]^3 after (x - center) / scale.
        Plain Python arithmetic: torch.compile traces through it without a graph break (through numpy it broke
        the trainer's compiled map terms into six graphs)."""
        return max(float(h) - float(l) for l, h in zip(self.lo, self.hi)) / 2

    def as_bounds(self) -> list[list[float]]:
        return [list(map(float, self.lo)), list(map(float, self.hi))]

    @classmethod
    def from_frustum(cls, camera, valid: np.ndarray, depth_range, margin: float = 0.02) -> "Volume":
        """Box around the camera frustum of the `valid` pixels [H, W] between the near and far depth."""
        v, u = np.nonzero(valid)
        if u.size == 0:
            raise ValueError("no valid pixel to define the working volume")
        step = max(1, u.size // 20000)  # a subsample of the valid pixels bounds the frustum well enough
        d = camera.pixel_to_ray(np.stack([u[::step], v[::step]], -1).astype(np.float64))
        d = d / d[:, 2:3]  # points at unit depth
        corners = np.concatenate([d * depth_range[0], d * depth_range[1]])
        lo, hi = corners.min(0), corners.max(0)
        pad = (hi - lo).max() * margin
        return cls(tuple((lo - pad).tolist()), tuple((hi + pad).tolist()))


def register_volume_buffers(module: nn.Module, volume: Volume, far: float | None) -> None:
    """Give an SDF module the per-scan numbers its forward reads: `center` [3] (float32, saved with the weights),
    and, not saved, `scale_mm` (the volume's scale) and `prior_mm` (the camera prior's radius `far`, when given) as
    0-d float32 buffers (float32 as a Python float meets a float32 tensor). As tensors they are inputs of
    torch.compile's graphs, not constants: the graphs compiled for one scan serve the next scan of the same
    sizes (as floats, every working volume recompiled them)."""
    module.register_buffer("center", torch.tensor(volume.center, dtype=torch.float32))
    module.register_buffer("scale_mm", torch.tensor(float(volume.scale), dtype=torch.float32), persistent=False)
    if far is not None:
        module.register_buffer("prior_mm", torch.tensor(float(far), dtype=torch.float32), persistent=False)


class PositionalEncoding(nn.Module):
    """[x, sin(2^k x), cos(2^k x) for k < n_freqs] (NeuS's embedder with log-sampled bands)."""

    def __init__(self, n_freqs: int = 6):
        super().__init__()
        self.register_buffer("freqs", 2.0 ** torch.arange(n_freqs, dtype=torch.float32), persistent=False)
        self.out_dim = 3 + 6 * n_freqs

    def forward(self, x):
        xf = x[..., None, :] * self.freqs[:, None]  # [..., F, 3]
        enc = torch.stack([torch.sin(xf), torch.cos(xf)], dim=-2)  # [..., F, 2, 3]
        return torch.cat([x, enc.flatten(-3)], dim=-1)


def geometric_init(lin: nn.Linear, i: int, n: int, radius: float, residual: bool, coords_only: bool) -> None:
    """NeuS/SAL geometric initialisation of layer i of n (in place): the network starts as |x| - radius in
    normalised units, or near 0 when it is a residual on a prior. coords_only: the first layer reads only the
    first 3 inputs (the coordinates; encodings and grid features start at weight 0)."""
    with torch.no_grad():
        out_dim, in_dim = lin.weight.shape
        if i == n - 1:
            if residual:
                lin.weight.normal_(0.0, 1e-4)
                lin.bias.zero_()
            else:
                lin.weight.normal_(math.sqrt(math.pi) / math.sqrt(in_dim), 1e-4)
                lin.bias.fill_(-radius)
            return
        lin.bias.zero_()
        lin.weight.normal_(0.0, math.sqrt(2.0) / math.sqrt(out_dim))
        if i == 0 and coords_only:
            lin.weight[:, 3:] = 0.0  # start from the raw coordinates only


class NeuSField(nn.Module):
    """NeuS's SDF MLP in mm (see module docstring).

    hidden x layers linear layers with Softplus(beta=100), a skip connection re-injecting the encoded input
    into layer `skip` (scaled by 1/sqrt 2), weight normalisation, and geometric initialisation:
    init="sphere" (NeuS): a sphere of radius `init_radius` (normalised units) at the volume's centre;
    init="camera": f = (far - |x|) + mlp, the MLP starting near 0: free space inside a sphere of radius
    `far` (mm) around the camera, i.e. a surface at the far depth behind everything.
    NeuS defaults: 256 x 8, skip 4, 6 frequencies.
    """

    def __init__(self, volume: Volume, hidden: int = 256, layers: int = 8, skip: int | None = 4, n_freqs: int = 6,
                 init: str = "sphere", init_radius: float = 0.5, weight_norm: bool = True, beta: float = 100.0,
                 far: float | None = None):
        super().__init__()
        if init not in ("sphere", "camera"):
            raise ValueError(f"init must be 'sphere' or 'camera', got {init!r}")
        self.volume = volume
        self.scale = float(volume.scale)
        self.prior_radius = None
        if init == "camera":
            # f(x) = far - |x| + residual(x): free space inside a sphere of radius `far` around the camera, so
            # every camera ray meets a surface at the far depth from the first iteration and carves forward
            if far is None:
                raise ValueError("init='camera' needs the far depth (mm)")
            self.prior_radius = float(far)
        register_volume_buffers(self, volume, self.prior_radius)
        self.encoding = PositionalEncoding(n_freqs) if n_freqs > 0 else None
        d_in = self.encoding.out_dim if self.encoding is not None else 3
        self.skip = skip if skip is not None and 0 < skip < layers else None
        self.beta = beta
        self.config = dict(hidden=hidden, layers=layers, skip=skip, n_freqs=n_freqs, init=init, init_radius=init_radius,
                           weight_norm=weight_norm, beta=beta)
        dims = [d_in] + [hidden] * layers + [1]
        self.linears = nn.ModuleList()
        for i in range(len(dims) - 1):
            out_dim = dims[i + 1] - d_in if self.skip is not None and i + 1 == self.skip else dims[i + 1]
            lin = nn.Linear(dims[i], out_dim)
            geometric_init(lin, i, len(dims) - 1, init_radius, residual=self.prior_radius is not None,
                           coords_only=self.encoding is not None)
            if self.skip is not None and i == self.skip and self.encoding is not None:
                with torch.no_grad():  # the skip input's encoding starts at weight 0 too
                    lin.weight[:, -(d_in - 3):] = 0.0
            self.linears.append(parametrizations.weight_norm(lin) if weight_norm else lin)

    def normalized_sdf(self, xn: torch.Tensor) -> torch.Tensor:
        """SDF in normalised units at normalised points [..., 3] -> [...]."""
        inp = self.encoding(xn) if self.encoding is not None else xn
        h = inp
        last = len(self.linears) - 1
        for i, lin in enumerate(self.linears):
            if self.skip is not None and i == self.skip:
                h = torch.cat([h, inp], dim=-1) / math.sqrt(2.0)
            h = lin(h)
            if i < last:
                h = F.softplus(h, beta=self.beta)
        return h[..., 0]

    def value_and_gradient(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(f(x) [...], grad f(x) [..., 3]) with the gradient written out explicitly.

        The input gradient is the MLP's backward pass spelled as ordinary tensor operations (softplus'
        = sigmoid(beta z)), so training needs only first-order autograd through it instead of a double
        backward, and torch.compile can fuse the whole thing. Equal to autograd's gradient (tested).
        """
        lead = x.shape[:-1]
        xn = ((x - self.center) / self.scale_mm).reshape(-1, 3)
        if self.encoding is not None:
            freqs = self.encoding.freqs
            xf = xn[:, None, :] * freqs[:, None]  # [P, F, 3]
            sin, cos = torch.sin(xf), torch.cos(xf)
            inp = torch.cat([xn, torch.stack([sin, cos], dim=-2).flatten(1)], dim=-1)
        else:
            inp = xn
        weights = [lin.weight for lin in self.linears]  # weight norm evaluated once
        h = inp
        pre = []
        last = len(self.linears) - 1
        inv_sqrt2 = 1.0 / math.sqrt(2.0)
        for i, lin in enumerate(self.linears):
            if self.skip is not None and i == self.skip:
                h = torch.cat([h, inp], dim=-1) * inv_sqrt2
            z = F.linear(h, weights[i], lin.bias)
            if i < last:
                pre.append(z)
                h = F.softplus(z, beta=self.beta)
        f = z[:, 0]
        g = weights[last][0].expand(xn.shape[0], -1)  # d f / d h_last
        g_skip = None
        for i in range(last - 1, -1, -1):
            bz = self.beta * pre[i]
            # softplus' = sigmoid(beta z), and exactly 1 where torch's softplus turns linear (beta z > 20)
            g = (g * torch.where(bz > 20.0, torch.ones_like(bz), torch.sigmoid(bz))) @ weights[i]
            if self.skip is not None and i == self.skip:
                d_in = inp.shape[1]
                g_skip = g[:, -d_in:] * inv_sqrt2
                g = g[:, :-d_in] * inv_sqrt2
        g_inp = g if g_skip is None else g + g_skip
        grad = g_inp[:, :3]
        if self.encoding is not None:
            gs = g_inp[:, 3:].reshape(-1, freqs.shape[0], 2, 3)
            grad = grad + ((gs[:, :, 0] * cos - gs[:, :, 1] * sin) * freqs[:, None]).sum(1)
        f = f * self.scale_mm  # f_mm(x) = scale f_n((x - c) / scale): the gradient is unchanged
        grad = grad.reshape(*lead, 3)
        f = f.reshape(lead)
        if self.prior_radius is not None:
            r = torch.linalg.norm(x, dim=-1, keepdim=True)
            f = f + (self.prior_mm - r[..., 0])
            grad = grad - x / r.clamp(min=1e-9)
        return f, grad

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x [..., 3] camera frame (mm) -> signed distance [...] (mm), positive outside."""
        f = self.normalized_sdf((x - self.center) / self.scale_mm) * self.scale_mm
        if self.prior_radius is not None:
            f = f + (self.prior_mm - torch.linalg.norm(x, dim=-1))
        return f


def auto_finest_resolution(volume: Volume, pixel_mm: float) -> int:
    """Cells per side of a hash grid's finest level that match a pixel footprint `pixel_mm` (mm, at the working
    depth): the power of two nearest (in log scale) to the volume's largest side over it. 2048 (0.39 mm cells)
    on the default rig, 512 (1.5 mm) on the small one; finer cells failed on the small rig (notes/hashgrid.md)."""
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
    from .hashgrid import HashGridSDF

    finest = config.grid_finest
    if finest == "auto":
        if pixel_mm is None:
            raise ValueError("make_field: grid_finest 'auto' needs the pixel footprint pixel_mm (mm)")
        finest = max(config.grid_base, auto_finest_resolution(volume, pixel_mm))
    return HashGridSDF(volume, levels=config.grid_levels, log2_table_size=config.grid_log2_table,
                       base_resolution=config.grid_base, finest_resolution=finest, hidden=config.grid_hidden,
                       layers=config.grid_layers, activation=config.grid_activation, gradient=config.grid_gradient,
                       init=init, far=far, active_levels=config.grid_start_levels)


class LearnedVariance(nn.Module):
    """NeuS's learned inverse standard deviation: inv_s = exp(10 v) / length_scale (1/mm), v starts at 0.3.

    `length_scale` is the field's normalisation scale (mm), so the initial sharpness matches NeuS's.
    """

    def __init__(self, init: float = 0.3, length_scale: float = 1.0):
        super().__init__()
        self.v = nn.Parameter(torch.tensor(float(init)))
        self.length_scale = float(length_scale)

    def forward(self) -> torch.Tensor:
        return torch.exp(self.v * 10.0) / self.length_scale


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
