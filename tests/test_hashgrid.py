"""The hash-grid encoding and HashGridSDF: Warp kernels against the torch twin (forward and backward),
float64 gradcheck of the twin, hand-computed grid cases (vertex, cell centre, cell face, clamped edge, hash
collision), the field's analytic gradient against finite differences and a float64 reference, the
tetrahedral finite-difference gradient, initialisation, inactive levels, torch.compile and CUDA graphs.

Tolerances (float32 Warp vs float32 twin): the same products summed in another order (and table
gradients accumulated by atomics in another order), so relative agreement to ~1e-6 of the largest value.
"""
import math

import pytest
import torch

from slwarp.neural.fields import Volume
from slwarp.neural.fields.hashgrid import TETRAHEDRON, HashGridLayout, HashGridSDF, hashgrid_encode, hashgrid_gradient
from slwarp.neural.ops.hashgrid_ops import PRIMES, twin_encode, twin_gradient

VOL = Volume((-400.0, -300.0, 434.0), (400.0, 300.0, 1116.0))
# 6 levels: 4 and 7 cells dense; 12, 21, 37 and 64 hashed into 2^10 entries
SMALL = HashGridLayout(levels=6, features=2, log2_table_size=10, base_resolution=4, finest_resolution=64)


def grid_inputs(layout=SMALL, P=96, device="cpu", dtype=torch.float32, seed=0, outside=True):
    g = torch.Generator().manual_seed(seed)
    lo, hi = (-0.1, 1.1) if outside else (0.02, 0.98)
    x = torch.rand(P, 3, generator=g, dtype=torch.float64) * (hi - lo) + lo
    table = torch.randn(layout.n_entries, layout.features, generator=g, dtype=torch.float64)
    cot = torch.randn(P, layout.levels * layout.features, generator=g, dtype=torch.float64)
    cast = lambda t: t.to(device=device, dtype=dtype)  # noqa: E731
    return cast(x), cast(table), cast(cot), layout.meta(device)


def active_tensor(n, device="cpu"):
    return torch.tensor([n], dtype=torch.int32, device=device)


def close(a, b, rel=2e-6, what=""):
    """|a - b| <= rel * max|b| (+ a floor for all-zero references)."""
    assert torch.isfinite(a).all(), f"{what}: non-finite values"
    tol = rel * max(b.abs().max().item(), 1.0)
    err = (a.double().cpu() - b.double().cpu()).abs().max().item()
    assert err <= tol, f"{what}: max error {err:.3g} > {tol:.3g}"


def test_layout():
    d = HashGridLayout()
    r = d.resolutions
    assert len(r) == 16 and r[0] == 16 and r[-1] == 2048
    growth = [b / a for a, b in zip(r, r[1:])]
    assert all(abs(q - 128 ** (1 / 15)) < 0.05 for q in growth)  # geometric up to rounding
    # dense while (res + 1)^3 <= 2^19: 16, 22, 31, 42, 58 cells; 81 cells (82^3 = 551368) is hashed
    assert d.hashed == [False] * 5 + [True] * 11
    assert d.sizes[:5] == [(x + 1) ** 3 for x in r[:5]] and set(d.sizes[5:]) == {1 << 19}
    assert d.offsets[1] == 17**3 and d.n_entries == sum(d.sizes)
    assert SMALL.resolutions == [4, 7, 12, 21, 37, 64] and SMALL.hashed == [False, False, True, True, True, True]
    meta = SMALL.meta()
    assert meta.dtype == torch.int32 and meta[3].tolist() == [21, 125 + 512 + 1024, 1024, 1]
    for bad in (dict(levels=0), dict(features=0), dict(log2_table_size=30), dict(base_resolution=64, finest_resolution=32)):
        with pytest.raises(ValueError, match="HashGridLayout"):
            HashGridLayout(**bad)


# F = 2 and 4 add a table row in one vector reduction on sm_90+ GPUs (kernels/hashgrid.py), 1 and 3 per component
@pytest.mark.parametrize("features,active", [(2, 6), (2, 4), (1, 6), (3, 6), (4, 6)])
def test_warp_matches_twin(device, features, active):
    layout = HashGridLayout(6, features, 10, 4, 64)
    x, table, cot, meta = grid_inputs(layout, device=device)
    act = active_tensor(active, device)
    results = {}
    for backend in ("warp", "torch"):
        xx, tt, gg = (t.clone().requires_grad_() for t in (x, table, cot))
        feat = hashgrid_encode(xx, tt, meta, act, backend=backend)
        grad = hashgrid_gradient(xx, tt, gg, meta, act, backend=backend)
        g = torch.Generator().manual_seed(1)
        w_feat = torch.randn(feat.shape, generator=g).to(device)
        w_grad = torch.randn(grad.shape, generator=g).to(device)
        loss = (feat * w_feat).sum() + (grad * w_grad).sum()
        results[backend] = (feat.detach(), grad.detach(), *torch.autograd.grad(loss, [xx, tt, gg]))
    names = ("features", "gradient", "d x", "d table", "d g")
    for name, w, t in zip(names, results["warp"], results["torch"]):
        close(w, t, what=name)
    if active < layout.levels:
        assert (results["warp"][0][:, active * features:] == 0).all()


def test_backward_sums_runs_of_points_in_one_cell(device):
    """The table gradient sums runs of consecutive points in one cell in registers (BACKWARD_RUN per thread):
    samples along rays, many consecutive ones sharing a coarse cell, some jumping back to an earlier cell, and
    a point count that leaves the last thread's run short, against the twin."""
    from slwarp.neural.ops.hashgrid_ops import BACKWARD_RUN

    g = torch.Generator().manual_seed(3)
    rays, n = 7, 13  # 91 points: not a multiple of the run
    origin = torch.rand(rays, 1, 3, generator=g, dtype=torch.float64) * 0.3 + 0.1
    direction = torch.rand(rays, 1, 3, generator=g, dtype=torch.float64) * 0.5 + 0.1
    t = torch.linspace(0, 1, n, dtype=torch.float64)[None, :, None]
    x = (origin + t * direction).reshape(-1, 3)
    x[20] = x[5]  # back to a cell left earlier in the run
    assert x.shape[0] % BACKWARD_RUN != 0
    table = torch.randn(SMALL.n_entries, SMALL.features, generator=g, dtype=torch.float64)
    w = torch.randn(x.shape[0], SMALL.levels * SMALL.features, generator=g, dtype=torch.float64)
    meta, act = SMALL.meta(device), active_tensor(SMALL.levels, device)
    grads = []
    for backend in ("warp", "torch"):
        tt = table.to(device=device, dtype=torch.float32).requires_grad_()
        feat = hashgrid_encode(x.to(device=device, dtype=torch.float32), tt, meta, act, backend=backend)
        grads.append(torch.autograd.grad((feat * w.to(device=device, dtype=torch.float32)).sum(), tt)[0])
    # the run really shares cells: at the coarsest level (4 cells) most neighbours along a ray are in one cell
    cells = torch.floor(x * 4)
    assert (cells[1:] == cells[:-1]).all(1).float().mean() > 0.5
    close(grads[0], grads[1], what="d table")


def test_twin_gradcheck_float64():
    layout = HashGridLayout(levels=3, features=2, log2_table_size=6, base_resolution=2, finest_resolution=8)
    assert layout.hashed == [False, True, True]
    x, table, cot, meta = grid_inputs(layout, P=6, dtype=torch.float64, seed=2, outside=False)
    x[0, 1] = 1.05  # one clamped coordinate: constant features along it
    act = active_tensor(3)
    args = (x.requires_grad_(), table.requires_grad_(), cot.requires_grad_())
    assert torch.autograd.gradcheck(lambda a, b: twin_encode(a, b, meta, act), args[:2], eps=1e-7, atol=1e-6)
    assert torch.autograd.gradcheck(lambda a, b, c: twin_gradient(a, b, c, meta, act), args, eps=1e-7, atol=1e-5)


def test_gradient_op_is_the_jacobian_of_the_encoding():
    """hashgrid_gradient(x, g) = J(x)^T g with J the autograd Jacobian of the twin encoding (float64)."""
    x, table, cot, meta = grid_inputs(P=5, dtype=torch.float64, seed=4)
    act = active_tensor(6)
    J = torch.autograd.functional.jacobian(lambda a: twin_encode(a, table, meta, act), x)  # [P, LF, P, 3]
    expect = torch.einsum("pjqd,pj->qd", J, cot)
    for backend in ("torch", "warp"):
        out = hashgrid_gradient(x, table, cot, meta, act, backend=backend)
        close(out, expect, rel=1e-5 if backend == "warp" else 1e-12, what=backend)


def one_level(res, log2_size=10, features=2):
    return HashGridLayout(levels=1, features=features, log2_table_size=log2_size, base_resolution=res, finest_resolution=res)


def dense_row(v, res):
    return v[0] + (res + 1) * (v[1] + (res + 1) * v[2])


def hashed_row(v, size):
    return (v[0] * PRIMES[0] ^ v[1] * PRIMES[1] ^ v[2] * PRIMES[2]) % size


@pytest.mark.parametrize("backend", ["warp", "torch"])
@pytest.mark.parametrize("res,hashed", [(4, False), (20, True)])
def test_vertex_centre_face_and_edge_by_hand(device, backend, res, hashed):
    layout = one_level(res)
    assert layout.hashed == [hashed]
    size = layout.sizes[0]
    row = (lambda v: hashed_row(v, size)) if hashed else (lambda v: dense_row(v, res))
    table = torch.arange(size * 2, dtype=torch.float32).reshape(size, 2).to(device) * 0.01 - 3.0
    meta, act = layout.meta(device), active_tensor(1, device)

    def feat(p):
        return hashgrid_encode(torch.tensor([p], dtype=torch.float32, device=device), table, meta, act, backend=backend)[0]

    # on a grid vertex: exactly that vertex's entry
    v = (1, 3, 2)
    torch.testing.assert_close(feat([c / res for c in v]), table[row(v)], rtol=1e-6, atol=1e-6)
    # at a cell centre: the mean of the cell's 8 corners
    corners = [(1 + i, 2 + j, 0 + k) for i in (0, 1) for j in (0, 1) for k in (0, 1)]
    expect = torch.stack([table[row(c)] for c in corners]).mean(0)
    torch.testing.assert_close(feat([1.5 / res, 2.5 / res, 0.5 / res]), expect, rtol=1e-6, atol=1e-6)
    # on the face between two cells: the average of the face's 4 vertices, whichever cell claims it
    face = [(2, 1 + j, 3 + k) for j in (0, 1) for k in (0, 1)]
    expect = torch.stack([table[row(c)] for c in face]).mean(0)
    torch.testing.assert_close(feat([2 / res, 1.5 / res, 3.5 / res]), expect, rtol=1e-6, atol=1e-6)
    # the upper edge of the cube (x = 1, in the last cell) and beyond it (clamped): the last vertex's entry
    top = (res, 0, res)
    torch.testing.assert_close(feat([1.0, 0.0, 1.0]), table[row(top)], rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(feat([1.3, -0.2, 1.0 + 1e-3]), table[row(top)], rtol=1e-6, atol=1e-6)
    # clamped axes have zero spatial derivative; the free one keeps its trilinear slope res (T[v+1] - T[v])
    p = torch.tensor([[0.5 / res, -0.2, 1.3]], device=device)
    g = torch.tensor([[1.0, 0.0]], device=device)
    grad = hashgrid_gradient(p, table, g, meta, act, backend=backend)[0]
    slope = res * (table[row((1, 0, res))][0] - table[row((0, 0, res))][0])
    torch.testing.assert_close(grad, torch.stack([slope, torch.zeros_like(slope), torch.zeros_like(slope)]),
                               rtol=1e-4, atol=1e-4)  # float32 difference of two entries of ~10


def find_collision(res, size):
    """Two distinct vertices of a level with `res` cells that hash to the same row of a table of `size`."""
    seen = {}
    for vz in range(res + 1):
        for vy in range(res + 1):
            for vx in range(res + 1):
                r = hashed_row((vx, vy, vz), size)
                if r in seen:
                    return seen[r], (vx, vy, vz), r
                seen[r] = (vx, vy, vz)
    raise AssertionError("no collision")


@pytest.mark.parametrize("backend", ["warp", "torch"])
def test_hash_collision_gradients_add_up(device, backend):
    layout = one_level(12, log2_size=6)  # 13^3 vertices into 64 entries
    assert layout.hashed == [True]
    a, b, shared = find_collision(12, 64)
    meta, act = layout.meta(device), active_tensor(1, device)
    table = torch.randn(64, 2, generator=torch.Generator().manual_seed(0)).to(device).requires_grad_()
    x = torch.tensor([a, b], dtype=torch.float32, device=device) / 12
    feat = hashgrid_encode(x, table, meta, act, backend=backend)
    torch.testing.assert_close(feat[0], feat[1])  # both vertices read the shared entry
    torch.testing.assert_close(feat[0], table[shared].detach())
    cot = torch.tensor([[1.5, -2.0], [0.25, 4.0]], device=device)
    (d_table,) = torch.autograd.grad((feat * cot).sum(), table)
    torch.testing.assert_close(d_table[shared], cot.sum(0))
    assert d_table.abs().sum().item() == pytest.approx(cot.sum(0).abs().sum().item(), rel=1e-6)  # nothing elsewhere


def random_field(backend="warp", seed=0, amplitude=0.02, **kw):
    torch.manual_seed(seed)
    kw = {**dict(levels=6, log2_table_size=12, base_resolution=4, finest_resolution=64, layers=2, gradient="analytic"), **kw}
    f = HashGridSDF(VOL, backend=backend, **kw)
    with torch.no_grad():  # away from the initialisation, so that the grid and every layer matter
        f.table.uniform_(-amplitude, amplitude)
        for lin in f.linears:
            lin.weight.add_(torch.randn_like(lin.weight) * 0.1)
    return f


def volume_points(n, dtype=torch.float32, seed=0, device="cpu"):
    g = torch.Generator().manual_seed(seed)
    lo, hi = torch.tensor(VOL.lo, dtype=torch.float64), torch.tensor(VOL.hi, dtype=torch.float64)
    return (torch.rand(n, 3, generator=g, dtype=torch.float64) * (hi - lo) + lo).to(device=device, dtype=dtype)


@pytest.mark.parametrize("activation,gradient", [("softplus", "analytic"), ("relu", "analytic"),
                                                 ("softplus", "finite_difference")])
def test_field_warp_matches_float64_twin(device, activation, gradient):
    """Value, gradient and the parameter gradients of an Eikonal + value loss: the float32 Warp field
    against the same field in float64 with the torch-twin encoding (the reference)."""
    warp_field = random_field("warp", activation=activation, gradient=gradient).to(device)
    ref = random_field("torch", activation=activation, gradient=gradient).double()
    ref.load_state_dict(warp_field.state_dict())
    x = volume_points(64, device=device)
    out = {}
    for name, f, xx in (("warp", warp_field, x), ("ref", ref, x.cpu().double())):
        v, g = f.value_and_gradient(xx)
        loss = ((g.norm(dim=-1) - 1) ** 2).sum() + (v / f.scale).abs().sum()
        out[name] = (v.detach(), g.detach(), *torch.autograd.grad(loss, list(f.parameters())))
    names = ["f", "grad"] + [f"d {n}" for n, _ in warp_field.named_parameters()]
    for name, w, r in zip(names, out["warp"], out["ref"]):
        close(w, r, rel=2e-5, what=name)


@pytest.mark.parametrize("backend", ["warp", "torch"])
def test_analytic_gradient_matches_autograd_and_finite_differences(backend):
    f = random_field(backend).double() if backend == "torch" else random_field(backend)
    dt = torch.float64 if backend == "torch" else torch.float32
    x = volume_points(32, dtype=dt, seed=1)
    _, grad = f.value_and_gradient(x)
    xr = x.clone().requires_grad_()
    (auto,) = torch.autograd.grad(f(xr).sum(), xr)  # autograd in x runs the gradient op as the encoding's backward
    close(grad, auto, rel=1e-5, what="autograd")
    if backend == "torch":  # central differences need float64 (float32 values of ~500 mm carry 3e-5 mm noise)
        eps = 1e-4  # mm; cells are 12.5 mm
        fd = torch.stack([(f(x + eps * e) - f(x - eps * e)) / (2 * eps) for e in torch.eye(3, dtype=dt)], -1)
        close(grad, fd, rel=1e-6, what="central differences")


def prior_only_field(gradient: str, finest_resolution: int) -> HashGridSDF:
    """The camera prior f = far - |x| (far 1000 mm) alone: zero tables, the MLP's output layer zero (float64)."""
    f = HashGridSDF(VOL, init="camera", far=1000.0, gradient=gradient, levels=2, log2_table_size=8, base_resolution=4,
                    finest_resolution=finest_resolution, backend="torch").double()
    with torch.no_grad():
        f.table.zero_()
        f.linears[-1].weight.zero_()
        f.linears[-1].bias.zero_()
    return f


def same_field_two_gradients(a: str, b: str, n: int, seed: int):
    """((field_a, field_b), (value, gradient) of a, of b) at n float64 volume points: one random field (the same
    parameters) with two gradient schemes."""
    fa = random_field("torch", gradient=a).double()
    fb = random_field("torch", gradient=b).double()
    fb.load_state_dict(fa.state_dict())
    x = volume_points(n, dtype=torch.float64, seed=seed)
    return (fa, fb), fa.value_and_gradient(x), fb.value_and_gradient(x)


def test_finite_difference_gradient():
    assert HashGridSDF(VOL, levels=2, log2_table_size=8).gradient == "finite_difference"  # the default
    (analytic, fd), (v_a, g_a), (v_f, g_f) = same_field_two_gradients("analytic", "finite_difference", 200, seed=2)
    torch.testing.assert_close(v_f, v_a)
    assert fd.finite_difference_step().item() == pytest.approx(800.0 / 64)  # finest cell: 2 scale / 64
    # taps one cell apart average the gradient over the cell: close to the exact one, not equal
    rel = ((g_f - g_a).norm(dim=-1) / g_a.norm(dim=-1)).median().item()
    assert 1e-4 < rel < 0.3
    # on a linear function the 4 taps are exact: the camera prior far - |x| far from its centre, no MLP
    lin = prior_only_field("finite_difference", finest_resolution=8)
    x = volume_points(10, dtype=torch.float64) + torch.tensor([0.0, 0.0, 1e6], dtype=torch.float64)
    _, g = lin.value_and_gradient(x)
    torch.testing.assert_close(g, -x / x.norm(dim=-1, keepdim=True), rtol=1e-6, atol=1e-6)
    lin.set_active_levels(1)
    assert lin.finite_difference_step().item() == pytest.approx(800.0 / 4)


def test_four_tap_value_is_the_taps_mean():
    """finite_difference_4: the gradient of the 5-evaluation scheme, the value from the 4 taps' mean, which
    is f + h^2 lap f / 2: h^2 / r below f = far - |x| at radius r."""
    (five, four), (v5, g5), (v4, g4) = same_field_two_gradients("finite_difference", "finite_difference_4", 50, seed=4)
    x = volume_points(50, dtype=torch.float64, seed=4)
    torch.testing.assert_close(g4, g5)
    h = five.finite_difference_step().item()
    e = torch.tensor(TETRAHEDRON, dtype=torch.float64)
    taps = torch.stack([five(x + h * ei) for ei in e])
    torch.testing.assert_close(v4, taps.mean(0))
    assert not torch.allclose(v4, v5)
    # the sphere prior far - |x| (tables and MLP zero) at radius r: the mean lies h^2 / r below f
    sph = prior_only_field("finite_difference_4", finest_resolution=64)
    r = 900.0
    d = torch.nn.functional.normalize(torch.randn(20, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(5)), dim=-1)
    v, _ = sph.value_and_gradient(r * d)
    hs = sph.finite_difference_step().item()
    assert hs == pytest.approx(12.5)  # h^2 / r = 0.17 mm; the next (third-order) term is near h^3 / r^2 = 0.002 mm
    torch.testing.assert_close(v, torch.full_like(v, 1000.0 - r - hs**2 / r), rtol=0, atol=0.05 * hs**2 / r)


def test_geometric_initialisation():
    c = torch.tensor(VOL.center, dtype=torch.float32)
    d = torch.nn.functional.normalize(torch.randn(500, 3, generator=torch.Generator().manual_seed(1)), dim=-1)
    for activation in ("relu", "softplus"):
        torch.manual_seed(0)
        f = HashGridSDF(VOL, hidden=256, activation=activation)
        # softplus(0) = ln 2 / beta lifts the sum of the 256 last-layer terms by up to sqrt(256 pi) ln 2 / 100
        # (at the centre, less where |x_n| grows); ReLU has no offset
        lift = 0.0 if activation == "relu" else math.sqrt(256 * math.pi) * math.log(2.0) / 100.0
        for r in (0.3, 0.5, 0.7):
            err = f(c + d * r * VOL.scale) / VOL.scale - (r - 0.5)  # against |x_n| - 0.5 in normalised units
            # over directions: |x_n| on average (the network's sum of |w| is within a few %), with a spread
            # of ~sqrt(2 pi / width) / 2 of |x_n| per direction
            assert -0.02 * r - 0.01 < err.mean().item() < lift + 0.02 * r + 0.01 and err.abs().max().item() < 0.35 * r + lift
        assert f(c[None]).item() < 0 < f((c + torch.tensor([0.0, 0.0, 0.9 * VOL.scale]))[None]).item()
    assert f.table.abs().max().item() <= 1e-4
    cam = HashGridSDF(VOL, init="camera", far=1000.0)
    x = torch.tensor([[0.0, 0.0, 500.0], [0.0, 0.0, 1200.0]])
    v, g = cam.value_and_gradient(x)
    assert abs(v[0].item() - 500.0) < 1.0 and abs(v[1].item() + 200.0) < 1.0
    assert torch.allclose(g.norm(dim=-1), torch.ones(2), atol=1e-2)


@pytest.mark.parametrize("backend", ["warp", "torch"])
def test_inactive_levels_have_zero_gradient(device, backend):
    f = random_field(backend).to(device)
    f.set_active_levels(3)
    off = f.layout.offsets[3]
    x = volume_points(64, device=device)
    v, g = f.value_and_gradient(x)
    loss = ((g.norm(dim=-1) - 1) ** 2).sum() + v.abs().sum()
    (d_table,) = torch.autograd.grad(loss, [f.table])
    assert (d_table[off:] == 0).all() and d_table[:off].abs().sum() > 0
    feat = hashgrid_encode(x.new_zeros(4, 3) + 0.3, f.table, f.meta, f.active, backend=backend)
    assert (feat[:, 3 * 2:] == 0).all() and feat[:, : 3 * 2].abs().sum() > 0
    # switching levels off and on changes the field without touching the tables
    f.set_active_levels(6)
    v6, _ = f.value_and_gradient(x)
    assert (v6 - v).abs().max() > 0
    for bad in (0, 7):
        with pytest.raises(ValueError, match="set_active_levels"):
            f.set_active_levels(bad)


def test_active_levels_travel_with_the_state_dict():
    f = random_field()
    f.set_active_levels(2)
    g = random_field(seed=1)
    g.load_state_dict(f.state_dict())
    assert g.n_active == 2 and g.active.item() == 2
    x = volume_points(8)
    torch.testing.assert_close(g(x), f(x))


def test_bad_input_is_named():
    f = random_field()
    with pytest.raises(ValueError, match=r"points must be \[P, 3\]"):
        hashgrid_encode(torch.zeros(4, 2), f.table, f.meta, f.active)
    with pytest.raises(ValueError, match="cotangent g"):
        hashgrid_gradient(torch.zeros(4, 3), f.table, torch.zeros(4, 5), f.meta, f.active)
    with pytest.raises(ValueError, match="backend"):
        hashgrid_encode(torch.zeros(4, 3), f.table, f.meta, f.active, backend="cuda")
    with pytest.raises(ValueError, match="init='camera' needs the far depth"):
        HashGridSDF(VOL, init="camera")
    with pytest.raises(ValueError, match="gradient must be"):
        HashGridSDF(VOL, gradient="numerical")


@pytest.mark.parametrize("gradient", ["analytic", "finite_difference"])
@pytest.mark.parametrize("backend", ["warp", "torch"])
def test_no_points(backend, gradient):
    f = random_field(backend, gradient=gradient)
    v, g = f.value_and_gradient(torch.zeros(0, 3))
    assert v.shape == (0,) and g.shape == (0, 3)
    (v.sum() + g.sum()).backward()
    assert (f.table.grad == 0).all()


def test_nan_points_stay_in_bounds(device):
    x, table, cot, meta = grid_inputs(P=4, device=device)
    x[1, 0] = float("nan")
    act = active_tensor(6, device)
    w = hashgrid_encode(x, table, meta, act)
    t = hashgrid_encode(x, table, meta, act, backend="torch")
    close(w, t, what="features at NaN")  # NaN reads as a clamped coordinate: no out-of-bounds index


@pytest.mark.parametrize("gradient", ["analytic", "finite_difference"])
def test_field_under_torch_compile_has_no_graph_break(gradient):
    f = random_field("warp", gradient=gradient)
    x = volume_points(32)

    def loss_fn(x):
        v, g = f.value_and_gradient(x)
        return ((g.norm(dim=-1) - 1) ** 2).mean() + v.abs().mean() / f.scale

    compiled = torch.compile(loss_fn, fullgraph=True, backend="aot_eager")
    params = list(f.parameters())
    lc = compiled(x)
    gc = torch.autograd.grad(lc, params)
    le = loss_fn(x)
    ge = torch.autograd.grad(le, params)
    torch.testing.assert_close(lc, le)
    for a, b in zip(gc, ge):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)


def test_field_in_the_renderer_trains():
    """A drop-in SDF module for StructuredLightRenderer: a few Adam steps lower the colour loss."""
    from slwarp.neural.render import StructuredLightRenderer
    from slwarp.sim.simulate import SimOptions, simulate_scene

    scan = simulate_scene("spheres", "random6", rig="small", options=SimOptions(seed=3))
    r = StructuredLightRenderer.from_scan(scan, torch.nn.Identity(), n_samples=16, n_importance=8, up_sample_steps=1)
    field = HashGridSDF(r.volume, init="camera", far=scan.depth_range[1], levels=8, log2_table_size=14,
                        finest_resolution=256)
    r.sdf = field
    opt = torch.optim.Adam([{"params": [field.table], "lr": 1e-2},
                            {"params": [p for n, p in field.named_parameters() if n != "table"], "lr": 1e-3}])
    g = torch.Generator().manual_seed(0)
    probe = r.sample_pixels(256, g)
    with torch.no_grad():
        before = r(probe, perturb=False).color.item()
    for _ in range(10):
        losses = r(r.sample_pixels(96, g), generator=g)
        loss = losses.color + 0.1 * losses.eikonal
        opt.zero_grad()
        loss.backward()
        opt.step()
        assert math.isfinite(loss.item())
    assert field.table.grad is not None and field.table.grad.abs().sum() > 0
    with torch.no_grad():
        assert r(probe, perturb=False).color.item() < before


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("gradient", ["analytic", "finite_difference"])
def test_cuda_graph_capture_of_forward_and_backward(gradient):
    f = random_field("warp", gradient=gradient).cuda()
    x = volume_points(512, device="cuda")

    def step():
        v, g = f.value_and_gradient(x)
        loss = ((g.norm(dim=-1) - 1) ** 2).mean() + v.abs().mean()
        return torch.autograd.grad(loss, list(f.parameters()))

    stream = torch.cuda.Stream()
    stream.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(stream):
        # warm-up on the side stream (kernels built, launches recorded); autograd's per-parameter nodes made
        # on the legacy stream would make the capture depend on it
        ref = step()
        step()
    torch.cuda.current_stream().wait_stream(stream)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        out = step()
    f.set_active_levels(3)  # a device tensor: the replay sees it without recapture
    graph.replay()
    torch.cuda.synchronize()
    f_eager = step()
    for a, b in zip(out, f_eager):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)
    assert any((a - b).abs().max() > 0 for a, b in zip(f_eager, ref))


def test_eager_functions_match_the_custom_ops(device):
    """Eager calls run autograd.Functions, torch.compile the custom ops (hashgrid_ops): the same values and the same
    first and second derivatives (the Eikonal term differentiates the spatial gradient into the table)."""
    from slwarp.neural.ops import hashgrid_ops as ops

    x, table, cot, meta = grid_inputs(device=device, seed=7)
    act = active_tensor(6, device)
    results = []
    for encode, gradient in ((ops._Encode.apply, ops._Gradient.apply), (ops._encode_op, ops._gradient_op)):
        xs, tab = x.clone().requires_grad_(), table.clone().requires_grad_()
        feat = encode(xs, tab, meta, act)
        gx = gradient(xs, tab, meta, act, cot)
        (d_x, d_table) = torch.autograd.grad((feat * cot).sum(), (xs, tab), create_graph=True)
        (dd_table,) = torch.autograd.grad((gx ** 2).sum() + (d_x ** 2).sum(), (tab,))
        results.append((feat, gx, d_x, d_table, dd_table))
    for name, a, b in zip(("features", "gradient", "d/dx", "d/dtable", "second derivative"), *results):
        close(a, b, rel=1e-6, what=name)


def test_eager_field_step_imports_no_dynamo():
    """A hash-grid field's forward and backward outside torch.compile import no torch._dynamo (its import is
    seconds of a fresh process; a custom op's first autograd call triggers it)."""
    import subprocess
    import sys

    code = ("import sys, torch\n"
            "from slwarp.neural.fields.hashgrid import hashgrid_encode, hashgrid_gradient, HashGridLayout\n"
            "lay = HashGridLayout(levels=2, features=2, log2_table_size=8, base_resolution=4, finest_resolution=8)\n"
            "x = torch.rand(16, 3, requires_grad=True); t = torch.randn(lay.n_entries, 2, requires_grad=True)\n"
            "a = torch.tensor([2], dtype=torch.int32)\n"
            "f = hashgrid_encode(x, t, lay.meta(), a); g = hashgrid_gradient(x, t, f.detach(), lay.meta(), a)\n"
            "(f.sum() + g.sum()).backward()\n"
            "print('torch._dynamo' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip().splitlines()[-1] == "False"
