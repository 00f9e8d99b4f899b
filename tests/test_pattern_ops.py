"""Pattern reprojection (`ops.reproject_patterns`): the Warp op against the torch twin (forward and backward into
the patterns and uv), float64 gradcheck of the twin, a finite-difference check of the Warp gradient into the
patterns, exact values at pixel centres, and NaN / far-away lookups.

Tolerances (float32 Warp vs float32 twin): the forward is the same four products summed in the same order, so it
agrees to an ulp or two. The gradient into a pattern pixel sums the contributions of every lookup around it,
with atomics in any order in the Warp kernel, so it agrees to a few ulps of the sum (rtol 1e-5, atol 1e-5).
"""
import pytest
import torch

from slwarp.neural import ops
from slwarp.neural.ops import twin

K, H, W = 3, 20, 30


def make_patterns(device="cpu", dtype=torch.float32, seed=0, k=K, h=H, w=W):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(k, h, w, generator=g, dtype=torch.float64).to(device=device, dtype=dtype)


def random_uv(n, seed=1, margin=2.5, away_from_integers=False, dtype=torch.float32, h=H, w=W):
    """n projector pixels [n, 2] uniform over the image grown by `margin` px on every side (some lookups are
    partly or wholly outside); away_from_integers: fractional parts in [0.1, 0.9] (bilinear is differentiable)."""
    g = torch.Generator().manual_seed(seed)
    lo = torch.tensor([-margin, -margin], dtype=torch.float64)
    span = torch.tensor([w - 1.0 + 2 * margin, h - 1.0 + 2 * margin], dtype=torch.float64)
    uv = lo + torch.rand(n, 2, generator=g, dtype=torch.float64) * span
    if away_from_integers:
        uv = torch.floor(uv) + 0.1 + 0.8 * (uv - torch.floor(uv))
    return uv.to(dtype)


# lookups on the image's edges and on pixel boundaries (integer and half-integer coordinates), partly outside
# (one or two taps in the image) and wholly outside, in pixels
EDGE_UV = [(0.0, 0.0), (W - 1.0, H - 1.0), (W - 1.0, 0.0), (0.0, H - 1.0), (7.0, 4.0), (7.5, 4.5), (7.0, 4.5),
           (-0.5, 5.25), (W - 0.5, 5.25), (3.25, -0.5), (3.25, H - 0.5), (-1.0, 6.0), (-0.999, 6.0), (W - 0.001, 2.0),
           (-1.001, 6.0), (W, 2.0), (W + 0.5, 2.0), (-3.0, -3.0), (W + 40.0, H + 40.0), (1.0e6, -1.0e6),
           (-1.0e30, 3.0), (5.0, 1.0e30)]
NON_FINITE_UV = [(float("nan"), 3.0), (4.0, float("nan")), (float("nan"), float("nan")), (float("inf"), 2.0),
                 (3.0, float("-inf"))]


def test_forward_matches_twin(device):
    pats = make_patterns(device)
    uv = torch.cat([random_uv(400), torch.tensor(EDGE_UV)]).to(device)
    uv = uv.reshape(2, -1, 2)  # leading dims: [..., 2] -> [..., K]
    out = ops.reproject_patterns(pats, uv)
    ref = ops.reproject_patterns(pats, uv, backend="torch")
    assert out.shape == (*uv.shape[:-1], K) and out.dtype == torch.float32
    torch.testing.assert_close(out.cpu(), ref.cpu(), rtol=1e-6, atol=1e-6)
    # some lookups see the patterns, the wholly outside ones see nothing
    flat = out.reshape(-1, K).cpu()
    assert (flat.abs().sum(1) > 0).sum() > 300
    far = torch.tensor([not (-1.0 <= u < W and -1.0 <= v < H) for u, v in EDGE_UV])
    assert torch.equal(flat[-len(EDGE_UV):][far], torch.zeros(int(far.sum()), K))


def test_strided_uv_gives_the_same_result(device):
    """uv with a non-contiguous last axis (a transposed [2, n] tensor) reads the same points."""
    pats = make_patterns(device)
    uv = random_uv(64, seed=4).to(device)
    strided = uv.t().contiguous().t()
    assert strided.stride(-1) != 1
    assert torch.equal(ops.reproject_patterns(pats, strided), ops.reproject_patterns(pats, uv))


def test_non_finite_uv_gives_zero(device):
    """NaN or infinite uv: zeros (not NaN) in the forward and zero gradients, and the finite lookups beside them
    are unaffected."""
    pats = make_patterns(device).requires_grad_()
    finite = random_uv(16, seed=2, away_from_integers=True)
    uv = torch.cat([finite, torch.tensor(NON_FINITE_UV)]).to(device).requires_grad_()
    out = ops.reproject_patterns(pats, uv)
    n = len(finite)
    assert torch.equal(out[n:].detach().cpu(), torch.zeros(len(NON_FINITE_UV), K))
    torch.testing.assert_close(out[:n].detach(), ops.reproject_patterns(pats.detach(), uv[:n].detach(), backend="torch"),
                               rtol=1e-6, atol=1e-6)
    g_pat, g_uv = torch.autograd.grad(out.sum(), [pats, uv])
    assert torch.isfinite(g_pat).all() and torch.isfinite(g_uv).all()
    assert torch.equal(g_uv[n:].cpu(), torch.zeros(len(NON_FINITE_UV), 2))
    # the pattern gradient is exactly that of the finite lookups alone
    ref = torch.autograd.grad(ops.reproject_patterns(pats, uv[:n].detach()).sum(), pats)[0]
    torch.testing.assert_close(g_pat, ref, rtol=0, atol=0)


@pytest.mark.parametrize("backend", ["warp", "torch"])
def test_integer_pixel_returns_the_pixel(device, backend):
    """A lookup at integer (u, v) is pattern pixel [v, u] itself, for every pixel of the image."""
    pats = make_patterns(device, seed=5)
    v, u = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    uv = torch.stack([u, v], -1).to(device=device, dtype=torch.float32)  # [H, W, 2]
    out = ops.reproject_patterns(pats, uv, backend=backend)  # [H, W, K]
    assert torch.equal(out.cpu(), pats.permute(1, 2, 0).cpu())


def _grads(pats, uv, cot, backend):
    p = pats.clone().requires_grad_()
    q = uv.clone().requires_grad_()
    out = ops.reproject_patterns(p, q, backend=backend)
    return torch.autograd.grad((out * cot).sum(), [p, q])


def test_backward_matches_twin(device):
    """Gradients into the patterns and uv of a random weighting of the outputs; 3000 lookups on 600 pixels, so
    many lookups scatter into each pixel (atomics that collide)."""
    pats = make_patterns(device, seed=6)
    uv = random_uv(3000, seed=7, away_from_integers=True).reshape(30, 100, 2).to(device)
    cot = torch.randn(30, 100, K, generator=torch.Generator().manual_seed(8)).to(device)
    gw_pat, gw_uv = _grads(pats, uv, cot, "warp")
    gt_pat, gt_uv = _grads(pats, uv, cot, "torch")
    assert gw_pat.shape == pats.shape and gw_uv.shape == uv.shape
    assert gt_pat.abs().min() > 0  # every pixel got some lookup: the comparison covers the whole image
    torch.testing.assert_close(gw_pat.cpu(), gt_pat.cpu(), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(gw_uv.cpu(), gt_uv.cpu(), rtol=1e-5, atol=1e-5)
    assert (gt_uv.abs() > 1e-3).float().mean() > 0.5


def test_gradients_on_edges_follow_the_twin(device):
    """On pixel boundaries and the image's edges bilinear has no derivative; both backends take the one of the
    cell floor(u), floor(v) (at u = -1 exactly: the slope into pixel 0; at u = W: none)."""
    pats = make_patterns(device, seed=21)
    uv = torch.tensor(EDGE_UV).to(device)
    cot = torch.randn(len(EDGE_UV), K, generator=torch.Generator().manual_seed(22)).to(device)
    gw_pat, gw_uv = _grads(pats, uv, cot, "warp")
    gt_pat, gt_uv = _grads(pats, uv, cot, "torch")
    torch.testing.assert_close(gw_pat.cpu(), gt_pat.cpu(), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(gw_uv.cpu(), gt_uv.cpu(), rtol=1e-5, atol=1e-6)
    assert gt_uv[EDGE_UV.index((-1.0, 6.0)), 0].abs() > 1e-3


def test_backward_of_one_input_at_a_time(device):
    """Only the patterns or only uv needing a gradient (pattern design: uv fixed) gives the same gradient as when
    both do; the inputs' dtypes come back (float64 patterns in, float64 gradient out)."""
    pats = make_patterns(device, seed=9)
    uv = random_uv(500, seed=10, away_from_integers=True).to(device)
    cot = torch.randn(500, K, generator=torch.Generator().manual_seed(11)).to(device)
    both_pat, both_uv = _grads(pats, uv, cot, "warp")
    p = pats.clone().requires_grad_()
    only_pat = torch.autograd.grad((ops.reproject_patterns(p, uv) * cot).sum(), p)[0]
    q = uv.clone().requires_grad_()
    only_uv = torch.autograd.grad((ops.reproject_patterns(pats, q) * cot).sum(), q)[0]
    torch.testing.assert_close(only_pat, both_pat, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(only_uv, both_uv, rtol=0, atol=0)
    p64 = pats.double().requires_grad_()
    g64 = torch.autograd.grad((ops.reproject_patterns(p64, uv) * cot).sum(), p64)[0]
    assert g64.dtype == torch.float64
    torch.testing.assert_close(g64.float(), both_pat, rtol=1e-5, atol=1e-6)


def test_twin_gradcheck_float64():
    pats = make_patterns(dtype=torch.float64, seed=12, k=2, h=5, w=6).requires_grad_()
    uv = random_uv(12, seed=13, margin=1.5, away_from_integers=True, dtype=torch.float64, h=5, w=6).requires_grad_()
    assert torch.autograd.gradcheck(twin.bilinear_patterns, (pats, uv), eps=1e-6, atol=1e-7, rtol=1e-6)


def test_warp_pattern_gradient_matches_finite_differences(device):
    """d loss / d P[k, y, x] of the Warp backward against a central difference of the Warp forward (the op is
    linear in the patterns, so the difference has no truncation error: only float32 rounding)."""
    pats = make_patterns(device, seed=14)
    # lookups around the probed pixels (corners, edges, inside) and at random elsewhere
    probes = [(0, 0, 0), (1, H - 1, W - 1), (2, 10, 15), (0, 0, 17), (1, 7, 0)]
    near = torch.tensor([(x + du, y + dv) for _, y, x in probes for du, dv in ((-0.3, 0.2), (0.45, -0.15), (0.1, 0.6))])
    uv = torch.cat([near, random_uv(200, seed=15, away_from_integers=True)]).to(device)
    cot = torch.randn(len(uv), K, generator=torch.Generator().manual_seed(16), dtype=torch.float64).to(device)
    g_pat, _ = _grads(pats, uv, cot.float(), "warp")

    def loss(p):  # in float64: the unchanged lookups cancel exactly between the two sides
        return (ops.reproject_patterns(p, uv).double() * cot).sum().item()

    eps = 0.05
    for k, y, x in probes:
        plus, minus = pats.clone(), pats.clone()
        plus[k, y, x] += eps
        minus[k, y, x] -= eps
        fd = (loss(plus) - loss(minus)) / (2 * eps)
        analytic = g_pat[k, y, x].item()
        assert abs(analytic) > 1e-2, f"probe {k, y, x} got no lookup"
        assert abs(fd - analytic) <= 1e-5 + 1e-5 * abs(fd), f"P[{k}, {y}, {x}]: fd {fd} vs backward {analytic}"


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_reproject_captures_in_a_cuda_graph(capture_cuda_graph):
    """Forward and backward into the patterns in one CUDA graph (no host synchronisation): the replay gives the
    eager gradient, also for new uv copied into the captured tensor."""
    pats = make_patterns("cuda", seed=17).requires_grad_()
    uv = random_uv(2000, seed=18).cuda()
    cot = torch.randn(2000, K, generator=torch.Generator().manual_seed(19)).cuda()

    def step():
        return torch.autograd.grad((ops.reproject_patterns(pats, uv) * cot).sum(), pats)[0]

    graph, g = capture_cuda_graph(step)
    uv.copy_(random_uv(2000, seed=20).cuda())
    graph.replay()
    torch.cuda.synchronize()
    torch.testing.assert_close(g, step(), rtol=1e-5, atol=1e-5)  # atomics: the order of the sums may differ
