"""A multiresolution hash-grid SDF field (Instant-NGP encoding + a small MLP), in millimetres.

    field = HashGridSDF(volume)                  # x [..., 3] camera frame (mm) -> signed distance [...] (mm)
    f, grad = field.value_and_gradient(x)        # grad [..., 3]: first-order autograd only (no double backward)
    field.set_active_levels(4)                   # coarse-to-fine: finer levels give zero features and gradients

Points are normalised by the working `Volume` as in `NeuSField` (x_n = (x - center) / scale in [-1, 1]^3)
and mapped to the grid's unit cube (x_n + 1) / 2, so the finest resolution counts cells over the volume's
largest side. L levels of F features grow geometrically from `base_resolution` to `finest_resolution`
cells (res_l = round(base b^l)); a level whose (res + 1)^3 vertices fit in the table size is dense, finer
ones are hashed (Instant-NGP's xor-of-primes hash, 2^log2_table_size entries). Features are trilinear; the
MLP (width 64, `layers` hidden layers, Softplus(beta=100) or ReLU) reads [x_n, features] and
f = scale mlp(...) (mm).

Spatial gradient (the Eikonal term and NeuS's cosine need it, differentiably; first-order autograd only):
- gradient="finite_difference" (the default): Neuralangelo's tetrahedral 4 taps,
  grad ~ sum_i e_i f(x + h e_i) / (4 h), e_i in {(1,-1,-1), (-1,-1,1), (-1,1,-1), (1,1,1)}, h = the finest
  active level's cell (mm, shrinking as levels switch on); 5 field evaluations per point (the centre gives f).
- gradient="finite_difference_4": the same 4 taps and no centre: f is their mean, f(x) + h^2 lap f(x) / 2
  (sum_i e_i e_i^T = 4 I), a bias of h^2 / r for a sphere of radius r (0.15 mm / r at the default rig's
  finest cell); 4 field evaluations instead of 5.
- gradient="analytic": the MLP's input gradient written out as tensor operations (as
  NeuSField.value_and_gradient) and the encoding's part by a fused op, grad_x = sum_j g_j d feat_j / dx,
  contracting the MLP cotangent g with the trilinear weights' spatial derivatives (kernels/hashgrid.py),
  with a hand-written backward into the tables, g and x.
Accuracy (bench/bench_field.py, CPU, a default field fitted to a bumpy sphere, points near its surface,
against the float64 analytic gradient): analytic float32 median relative error 1e-5 (exact up to
rounding); finite difference 15% (p99 51%): it is the gradient averaged over one cell, not the field's own.
Why it is the default anyway (docs/hashgrid.md, small rig, 3 scenes, CPU): trilinear features kink on
every cell face, and a V-shaped SDF across a face has |grad f| = 1 on both sides, so with the exact
gradient thin spurious sheets survive the Eikonal term (boxes: MAE 5.49 mm, 18% of pixels > 5 mm off);
the taps straddle the face and penalise them (boxes 0.64 mm; mean of bunny, vase, boxes 0.575 mm against
2.17 mm analytic and 0.749 mm for the `cpu` preset's MLP). Cost: a training step of the `cpu` preset
with an 8-level grid took 178 ms with finite differences, 97 ms analytic, 188 ms with the MLP (CPU, one
thread); the GPU figures come from bench/bench_field.py.

The encoding ops (`hashgrid_encode`, `hashgrid_gradient`: Warp kernels and their torch twins) live in
slwarp.neural.ops.hashgrid_ops and are importable from here.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F

from ..ops.hashgrid_ops import hashgrid_encode, hashgrid_gradient
from ..ops.launch import check_backend
from .mlp import geometric_init
from .volume import Volume, register_volume_buffers

__all__ = ["HashGridLayout", "HashGridSDF", "hashgrid_encode", "hashgrid_gradient"]

GRADIENTS = ("analytic", "finite_difference", "finite_difference_4")
ACTIVATIONS = ("softplus", "relu")
# tetrahedron vertices of Neuralangelo's 4-tap gradient: sum_i e_i e_i^T = 4 I
TETRAHEDRON = ((1.0, -1.0, -1.0), (-1.0, -1.0, 1.0), (-1.0, 1.0, -1.0), (1.0, 1.0, 1.0))


@dataclass(frozen=True)
class HashGridLayout:
    """Levels, features and table sizes of a multiresolution hash grid over the unit cube.

    levels L; features F per entry; log2_table_size: entries per hashed level (2^19 as Instant-NGP);
    base_resolution and finest_resolution: cells per side of the coarsest and finest level.
    """

    levels: int = 16
    features: int = 2
    log2_table_size: int = 19
    base_resolution: int = 16
    finest_resolution: int = 2048

    def __post_init__(self):
        if not 1 <= self.levels <= 64:
            raise ValueError(f"HashGridLayout: levels must be in 1..64, got {self.levels}")
        if not 1 <= self.features <= 16:
            raise ValueError(f"HashGridLayout: features must be in 1..16, got {self.features}")
        if not 4 <= self.log2_table_size <= 26:
            raise ValueError(f"HashGridLayout: log2_table_size must be in 4..26, got {self.log2_table_size}")
        if not 1 <= self.base_resolution <= self.finest_resolution:
            raise ValueError(f"HashGridLayout: need 1 <= base_resolution ({self.base_resolution}) <= finest_resolution "
                             f"({self.finest_resolution})")
        if self.finest_resolution > 1 << 20:
            raise ValueError(f"HashGridLayout: finest_resolution {self.finest_resolution} exceeds 2^20 cells")

    @property
    def resolutions(self) -> list[int]:
        """Cells per side of each level: geometric from base to finest."""
        if self.levels == 1:
            return [self.finest_resolution]
        growth = (self.finest_resolution / self.base_resolution) ** (1.0 / (self.levels - 1))
        return [max(1, round(self.base_resolution * growth**level)) for level in range(self.levels)]

    @property
    def hashed(self) -> list[bool]:
        """True for levels whose (res + 1)^3 vertices do not fit in a table of 2^log2_table_size."""
        return [(r + 1) ** 3 > (1 << self.log2_table_size) for r in self.resolutions]

    @property
    def sizes(self) -> list[int]:
        return [(1 << self.log2_table_size) if h else (r + 1) ** 3 for r, h in zip(self.resolutions, self.hashed)]

    @property
    def offsets(self) -> list[int]:
        out, total = [], 0
        for s in self.sizes:
            out.append(total)
            total += s
        return out

    @property
    def n_entries(self) -> int:
        """Rows of the table [E, F] holding all levels."""
        return sum(self.sizes)

    def meta(self, device=None) -> torch.Tensor:
        """[L, 4] int32 per level: (res, offset, size, hashed), as the kernels and the twin read it."""
        rows = [[r, o, s, int(h)] for r, o, s, h in zip(self.resolutions, self.offsets, self.sizes, self.hashed)]
        if self.n_entries >= 2**31:
            raise ValueError(f"HashGridLayout: {self.n_entries} table entries do not fit int32 indices")
        return torch.tensor(rows, dtype=torch.int32, device=device)


# ----------------------------------------------------------------------------------------------
# the field


class HashGridSDF(nn.Module):
    """Hash-grid SDF in mm: x [..., 3] camera frame -> signed distance [...] (see module docstring).

    volume: the working `Volume`; levels, features, log2_table_size, base_resolution, finest_resolution:
    the `HashGridLayout`; hidden (64) x layers (1 or 2) hidden layers with activation "softplus" (beta) or
    "relu"; init="sphere": NeuS's geometric initialisation, a sphere of radius init_radius (normalised
    units) at the volume's centre; init="camera": f = far - |x| + scale mlp, the MLP starting near 0 (a
    surface at the far depth around the camera); tables uniform in +-table_init; gradient "analytic" or
    "finite_difference"; backend "warp" or "torch" (the encoding's implementation); active_levels: levels
    switched on at the start (None: all).
    """

    def __init__(self, volume: Volume, *, levels: int = 16, features: int = 2, log2_table_size: int = 19,
                 base_resolution: int = 16, finest_resolution: int = 2048, hidden: int = 64, layers: int = 1,
                 activation: str = "softplus", beta: float = 100.0, init: str = "sphere", init_radius: float = 0.5,
                 far: float | None = None, table_init: float = 1e-4, gradient: str = "finite_difference",
                 backend: str = "warp", active_levels: int | None = None):
        super().__init__()
        if init not in ("sphere", "camera"):
            raise ValueError(f"HashGridSDF: init must be 'sphere' or 'camera', got {init!r}")
        if init == "camera" and far is None:
            raise ValueError("HashGridSDF: init='camera' needs the far depth (mm)")
        if activation not in ACTIVATIONS:
            raise ValueError(f"HashGridSDF: activation must be one of {ACTIVATIONS}, got {activation!r}")
        if gradient not in GRADIENTS:
            raise ValueError(f"HashGridSDF: gradient must be one of {GRADIENTS}, got {gradient!r}")
        check_backend(backend)
        if layers < 1 or hidden < 1:
            raise ValueError(f"HashGridSDF: need at least one hidden layer of width >= 1, got {layers} x {hidden}")
        self.layout = HashGridLayout(levels, features, log2_table_size, base_resolution, finest_resolution)
        self.volume = volume
        self.scale = float(volume.scale)
        self.activation, self.beta = activation, float(beta)
        self.gradient, self.backend = gradient, backend
        self.prior_radius = float(far) if init == "camera" else None
        self.config = dict(levels=levels, features=features, log2_table_size=log2_table_size,
                           base_resolution=base_resolution, finest_resolution=finest_resolution, hidden=hidden,
                           layers=layers, activation=activation, beta=beta, init=init, init_radius=init_radius,
                           table_init=table_init, gradient=gradient)
        register_volume_buffers(self, volume, self.prior_radius)
        self.register_buffer("meta", self.layout.meta(), persistent=False)
        # finest active level's cell (mm): the finite-difference step, read on the device
        cells = [2.0 * self.scale / r for r in self.layout.resolutions]
        self.register_buffer("cell_mm", torch.tensor(cells, dtype=torch.float32), persistent=False)
        self.register_buffer("active", torch.tensor([levels], dtype=torch.int32))
        # the finite-difference taps' directions live on the device: a host tensor copied inside a CUDA graph
        # capture is an error
        self.register_buffer("tetrahedron", torch.tensor(TETRAHEDRON, dtype=torch.float32), persistent=False)
        self.n_active = levels
        self.table = nn.Parameter(torch.empty(self.layout.n_entries, features).uniform_(-table_init, table_init))
        d_in = 3 + levels * features
        dims = [d_in] + [hidden] * layers + [1]
        self.linears = nn.ModuleList(nn.Linear(dims[i], dims[i + 1]) for i in range(len(dims) - 1))
        self._geometric_init(init_radius, residual=self.prior_radius is not None)
        if active_levels is not None:
            self.set_active_levels(active_levels)

    def _geometric_init(self, radius: float, residual: bool):
        """NeuS/SAL geometric initialisation on the coordinates (feature inputs start at weight 0): the
        network starts as |x_n| - radius, or near 0 as a residual of the camera prior."""
        for i, lin in enumerate(self.linears):
            geometric_init(lin, i, len(self.linears), radius, residual, coords_only=True)

    # --- levels -------------------------------------------------------------------------------
    @property
    def levels(self) -> int:
        return self.layout.levels

    def set_active_levels(self, n: int) -> None:
        """Switch on the n coarsest levels (1 <= n <= levels); the others give zero features and receive
        zero gradient. Written into a device tensor: no recompilation, and a captured CUDA graph sees it."""
        n = int(n)
        if not 1 <= n <= self.levels:
            raise ValueError(f"HashGridSDF.set_active_levels: n must be in 1..{self.levels}, got {n}")
        self.active.fill_(n)
        self.n_active = n

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)
        key = prefix + "active"
        if key in state_dict:
            self.n_active = int(state_dict[key].reshape(-1)[0])

    @property
    def finest_cell_mm(self) -> float:
        """Cell size (mm) of the finest level."""
        return 2.0 * self.scale / self.layout.resolutions[-1]

    # --- evaluation ---------------------------------------------------------------------------
    def _unit(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(x_n [P, 3] in [-1, 1]^3, x in the grid's unit cube [P, 3]) of camera-frame points [..., 3]."""
        xn = ((x - self.center) / self.scale_mm).reshape(-1, 3)
        return xn, xn * 0.5 + 0.5

    def _act(self, z: torch.Tensor) -> torch.Tensor:
        return F.softplus(z, beta=self.beta) if self.activation == "softplus" else F.relu(z)

    def _act_derivative(self, z: torch.Tensor) -> torch.Tensor:
        if self.activation == "relu":
            return (z > 0).to(z.dtype)
        bz = self.beta * z
        # softplus' = sigmoid(beta z), and exactly 1 where torch's softplus turns linear (beta z > 20)
        return torch.where(bz > 20.0, torch.ones_like(bz), torch.sigmoid(bz))

    def _features(self, x01: torch.Tensor, dtype) -> torch.Tensor:
        return hashgrid_encode(x01, self.table, self.meta, self.active, backend=self.backend).to(dtype)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x [..., 3] camera frame (mm) -> signed distance [...] (mm), positive outside."""
        xn, x01 = self._unit(x)
        h = torch.cat([xn, self._features(x01, xn.dtype)], dim=-1)
        last = len(self.linears) - 1
        for i, lin in enumerate(self.linears):
            h = lin(h)
            if i < last:
                h = self._act(h)
        f = (h[:, 0] * self.scale_mm).reshape(x.shape[:-1])
        if self.prior_radius is not None:
            f = f + (self.prior_mm - torch.linalg.norm(x, dim=-1))
        return f

    def value_and_gradient(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(f(x) [...] mm, grad f(x) [..., 3]): the gradient by the method in `self.gradient`, differentiable
        in the parameters with first-order autograd."""
        if self.gradient != "analytic":
            return self._finite_difference(x)
        lead = x.shape[:-1]
        xn, x01 = self._unit(x)
        feat = self._features(x01, xn.dtype)
        h = torch.cat([xn, feat], dim=-1)
        pre = []
        last = len(self.linears) - 1
        for i, lin in enumerate(self.linears):
            z = F.linear(h, lin.weight, lin.bias)
            if i < last:
                pre.append(z)
                h = self._act(z)
        f = z[:, 0] * self.scale_mm
        g = self.linears[last].weight[0].expand(xn.shape[0], -1)  # d f_n / d h_last
        for i in range(last - 1, -1, -1):
            g = (g * self._act_derivative(pre[i])) @ self.linears[i].weight
        # f_mm(x) = scale f_n(x_n, feat((x_n + 1) / 2)) with x_n = (x - c) / scale: d/dx = d/dx_n / scale
        # times scale, i.e. grad = g_xn + 0.5 g_unit
        g_feat = hashgrid_gradient(x01, self.table, g[:, 3:], self.meta, self.active, backend=self.backend)
        grad = g[:, :3] + 0.5 * g_feat.to(g.dtype)
        f, grad = f.reshape(lead), grad.reshape(*lead, 3)
        if self.prior_radius is not None:
            r = torch.linalg.norm(x, dim=-1, keepdim=True)
            f = f + (self.prior_mm - r[..., 0])
            grad = grad - x / r.clamp(min=1e-9)
        return f, grad

    def finite_difference_step(self) -> torch.Tensor:
        """The tetrahedral step h (mm) [1]: the finest active level's cell (a device tensor: no sync)."""
        return self.cell_mm[(self.active - 1).long()].to(self.center.dtype)

    def _finite_difference(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        lead = x.shape[:-1]
        pts = x.reshape(-1, 3)
        h = self.finite_difference_step()
        e = self.tetrahedron.to(pts.dtype)  # [4, 3]
        # point-major, a point's taps side by side: they lie within one finest cell of each other, so the encoding's
        # backward, which sums consecutive points of one cell in registers (BACKWARD_RUN), adds them to the table
        # in one atomic per corner at every coarser level
        taps = pts[:, None] + h * e[None]  # [P, 4, 3]
        if self.gradient == "finite_difference_4":  # f from the taps' mean: one evaluation fewer
            vals = self.forward(taps)  # [P, 4]
            f = vals.mean(1)
        else:
            vals = self.forward(torch.cat([pts[:, None], taps], 1))  # [P, 5]: the centre, then the 4 taps
            f, vals = vals[:, 0], vals[:, 1:]
        grad = (vals[:, :, None] * e[None]).sum(1) / (4.0 * h)
        return f.reshape(lead), grad.reshape(*lead, 3)

    def extra_repr(self) -> str:
        L = self.layout
        return (f"levels={L.levels} ({self.n_active} active), features={L.features}, table=2^{L.log2_table_size}, "
                f"resolution {L.base_resolution}..{L.finest_resolution} (finest cell {self.finest_cell_mm:.3g} mm), "
                f"{self.activation}, gradient={self.gradient}, backend={self.backend}")
