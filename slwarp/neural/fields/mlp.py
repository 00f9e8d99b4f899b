"""NeuS's SDF network (`NeuSField`, the paper's MLP) and its learned variance (`LearnedVariance`), in millimetres.

The renderer works in the camera frame in mm, so a field maps points x [..., 3] (mm) to signed distances
[...] (mm). `NeuSField` keeps NeuS's network in a normalised space: the working volume (an axis-aligned
box in the camera frame, from the scan's valid pixels between the near and far depth) is mapped into
[-1, 1]^3 by x_n = (x - center) / scale with scale = half the box's largest side, and
f(x) = scale * mlp(x_n): distances and gradients stay metric (|grad f| = 1 for a true SDF).
"""
from __future__ import annotations

import math

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch.nn.utils import parametrizations

from .volume import Volume, register_volume_buffers


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
