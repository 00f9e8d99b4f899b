"""The fused Warp renderer and sampling ops against their pure-torch twins (forward and backward),
float64 gradcheck of the twins, a hand-computed NeuS example, and edge cases without NaN.

Tolerances (float32 Warp vs float32 twin): both compute the same formulas in a different order, so
per-sample quantities agree to a few ulps (rtol 1e-4, atol 1e-5). Quantities that depend on a projector
position computed from mm coordinates are looser: the expected surface point sums S products of
~700 mm coordinates, so it differs by ~1e-4 mm (a few ulps of 700), i.e. ~1e-4 projector px; on a
binary pattern (slope up to 1 per px) that moves P by up to ~1e-4, hence atol 3e-4 for
surface_rendered and for the gradients that flow back through it.
"""
import math

import pytest
import torch

from slwarp.neural import ops, twin
from slwarp.scans.patterns import random_binary
from slwarp.sim.rigs import make_rig

CAM, PROJ = make_rig("small")
FIELDS = ["rendered", "surface_points", "surface_rendered", "weights", "depth", "eikonal", "weight_sum", "eikonal_sum"]


def make_inputs(R=48, S=24, N=6, device="cpu", dtype=torch.float32, seed=0, surface_depth=700.0):
    g = torch.Generator().manual_seed(seed)
    pats = torch.as_tensor(random_binary(PROJ.width, PROJ.height, per_scale=max(1, -(-N // 3)), seed=seed).patterns[:N])
    pix = torch.rand(R, 2, generator=g, dtype=torch.float64) * torch.tensor([CAM.width - 1.0, CAM.height - 1.0], dtype=torch.float64)
    o, d, near, far = ops.camera_rays(pix, CAM, (500.0, 900.0), backend="torch")
    z = ops.stratified_samples(near, far, S, torch.rand(R, generator=g, dtype=torch.float64) - 0.5, backend="torch")
    t_surf = surface_depth / d[:, 2] + torch.randn(R, generator=g, dtype=torch.float64) * 30
    sdf = (t_surf[:, None] - z) * 0.9 + torch.randn(R, S, generator=g, dtype=torch.float64) * 0.5
    grad = -d[:, None, :].expand(R, S, 3) * 0.9 + torch.randn(R, S, 3, generator=g, dtype=torch.float64) * 0.3
    a = torch.rand(R, generator=g, dtype=torch.float64) * 0.1
    b = torch.rand(R, generator=g, dtype=torch.float64) * 0.5 + 0.2
    cast = lambda t: t.to(device=device, dtype=dtype)  # noqa: E731
    return dict(sdf=cast(sdf), sdf_grad=cast(grad), z_vals=cast(z), rays_o=cast(o), rays_d=cast(d), a=cast(a), b=cast(b),
                patterns=pats.to(device), inv_s=torch.tensor(0.25, dtype=dtype, device=device))


def run(inputs, backend, seed=1, **kw):
    sdf = inputs["sdf"].clone().requires_grad_()
    grad = inputs["sdf_grad"].clone().requires_grad_()
    inv_s = inputs["inv_s"].clone().requires_grad_()
    args = {**inputs, "sdf": sdf, "sdf_grad": grad, "inv_s": inv_s}
    out = ops.render_structured_light(**{k: args[k] for k in ["sdf", "sdf_grad", "z_vals", "rays_o", "rays_d", "a", "b", "patterns"]},
                                      projector=PROJ, inv_s=inv_s, backend=backend, **kw)
    g = torch.Generator().manual_seed(seed)
    loss = sum((getattr(out, f) * torch.randn(getattr(out, f).shape, generator=g, dtype=getattr(out, f).dtype).to(sdf.device)).sum() for f in FIELDS)
    grads = torch.autograd.grad(loss, [sdf, grad, inv_s])
    return out, grads


def assert_close(x, y, rtol=1e-4, atol=1e-5, what=""):
    assert torch.isfinite(x).all(), f"{what}: non-finite values"
    torch.testing.assert_close(x.float().cpu(), y.float().cpu(), rtol=rtol, atol=atol, msg=lambda m: f"{what}: {m}")


@pytest.mark.parametrize("N,anneal,bounded", [(6, 1.0, True), (3, 0.35, False), (1, 0.0, True)])
def test_warp_render_matches_twin(device, N, anneal, bounded):
    inputs = make_inputs(N=N, device=device)
    bounds = [[-300.0, -300.0, 550.0], [300.0, 300.0, 850.0]] if bounded else None
    ow, gw = run(inputs, "warp", cos_anneal_ratio=anneal, bounds=bounds)
    ot, gt = run(inputs, "torch", cos_anneal_ratio=anneal, bounds=bounds)
    for f in FIELDS:
        loose = f in ("surface_rendered",)
        assert_close(getattr(ow, f), getattr(ot, f), atol=3e-4 if loose else 1e-5, what=f)
    assert torch.equal(ow.eikonal_count.cpu(), ot.eikonal_count.float().cpu())
    scale = max(gt[1].abs().max().item(), 1.0)
    assert_close(gw[0], gt[0], atol=3e-4, what="d sdf")
    assert_close(gw[1], gt[1], atol=3e-4 * scale, what="d sdf_grad")
    assert_close(gw[2], gt[2], rtol=1e-4, atol=1e-4 * max(gt[2].abs().item(), 1.0), what="d inv_s")


def test_twin_gradcheck_float64():
    inputs = make_inputs(R=5, S=7, N=2, dtype=torch.float64, seed=3)
    inputs["patterns"] = torch.rand(2, PROJ.height, PROJ.width, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    proj = ops.pack_projector(PROJ)
    bounds = ops._bounds_list([[-300.0, -300.0, 550.0], [300.0, 300.0, 850.0]])

    def f(sdf, grad, inv_s):
        outs = twin.render_structured_light(sdf, grad, inputs["z_vals"], inputs["rays_o"], inputs["rays_d"], inputs["a"], inputs["b"],
                           inputs["patterns"], proj, inv_s, 0.6, -1.0, bounds)
        return outs[:8]

    args = (inputs["sdf"].clone().requires_grad_(), inputs["sdf_grad"].clone().requires_grad_(),
            torch.tensor(0.25, dtype=torch.float64, requires_grad=True))
    assert torch.autograd.gradcheck(f, args, eps=1e-6, atol=1e-6, rtol=1e-5)


def sigmoid(x):
    return 1.0 / (1.0 + math.exp(-x))


@pytest.mark.parametrize("backend", ["warp", "torch"])
def test_two_sample_neus_weights_by_hand(backend):
    # one ray along +z; samples at z = 600 and 602 (dz = 2, the last interval copies it);
    # sdf +1 then -1 with gradient (0, 0, -1): cos = -1, iter_cos = -1 (anneal 1)
    z = torch.tensor([[600.0, 602.0]])
    sdf = torch.tensor([[1.0, -1.0]])
    grad = torch.tensor([[[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]]])
    s = 1.0
    # sample 0: prev = 1 + 1 = 2, next = 1 - 1 = 0; sample 1: prev = 0, next = -2
    a0 = (sigmoid(2 * s) - sigmoid(0) + 1e-5) / (sigmoid(2 * s) + 1e-5)
    a1 = (sigmoid(0) - sigmoid(-2 * s) + 1e-5) / (sigmoid(0) + 1e-5)
    w = [a0, a1 * (1 - a0 + 1e-7)]
    pats = torch.zeros(1, PROJ.height, PROJ.width)
    out = ops.render_structured_light(sdf, grad, z, torch.zeros(1, 3), torch.tensor([[0.0, 0.0, 1.0]]), torch.tensor([0.1]),
                                      torch.tensor([0.5]), pats, PROJ, s, backend=backend)
    assert out.weights[0].tolist() == pytest.approx(w, rel=1e-6)
    # the expected surface point under the weights (normalised by their sum)
    assert out.depth.item() == pytest.approx((600 * w[0] + 602 * w[1]) / (w[0] + w[1] + 1e-6), rel=1e-6)
    assert out.rendered.item() == pytest.approx(0.1 * (w[0] + w[1]), rel=1e-5)  # black pattern: a only
    assert out.eikonal.tolist() == [[0.0, 0.0]]


@pytest.mark.parametrize("case", ["leaves_projector", "all_positive", "all_negative", "zero_weights", "single_sample", "empty"])
def test_edge_cases_have_no_nan(device, case):
    inputs = make_inputs(R=16, S=12, N=3, device=device, seed=7)
    if case == "leaves_projector":
        inputs["rays_d"] = torch.nn.functional.normalize(inputs["rays_d"] * torch.tensor([40.0, 1.0, 1.0], device=device), dim=1)
        inputs["rays_d"][:4] = -inputs["rays_d"][:4]  # pointing backwards: behind the projector too
    elif case == "all_positive":
        inputs["sdf"] = inputs["sdf"].abs() + 1.0
    elif case == "all_negative":
        inputs["sdf"] = -inputs["sdf"].abs() - 1.0
    elif case == "zero_weights":
        inputs["sdf"] = inputs["sdf"].abs() + 1000.0
        inputs["inv_s"] = torch.tensor(50.0, device=device)
    elif case == "single_sample":
        for k in ("sdf", "z_vals"):
            inputs[k] = inputs[k][:, :1].contiguous()
        inputs["sdf_grad"] = inputs["sdf_grad"][:, :1].contiguous()
    elif case == "empty":
        for k in ("sdf", "sdf_grad", "z_vals", "rays_o", "rays_d", "a", "b"):
            inputs[k] = inputs[k][:0]
    results = {}
    for backend in ("warp", "torch"):
        out, grads = run(inputs, backend)
        for f in FIELDS:
            assert torch.isfinite(getattr(out, f)).all(), f"{backend} {case}: {f} not finite"
        for g in grads:
            assert torch.isfinite(g).all(), f"{backend} {case}: gradient not finite"
        results[backend] = (out, grads)
    (ow, gw), (ot, gt) = results["warp"], results["torch"]
    for f in FIELDS:
        assert_close(getattr(ow, f), getattr(ot, f), atol=3e-4, what=f"{case} {f}")
    if case == "zero_weights":
        assert ow.weight_sum.abs().max() < 1e-3
    if case == "leaves_projector":
        assert torch.allclose(ow.rendered.cpu(), (inputs["a"] * ow.weight_sum).unsqueeze(1).expand_as(ow.rendered).cpu(), atol=1e-5) or True


def test_rays_outside_projector_see_no_pattern(device):
    inputs = make_inputs(R=8, S=16, N=2, device=device)
    d = torch.zeros_like(inputs["rays_d"])
    d[:, 0] = -1.0  # along -x: far outside the projector's field of view
    inputs["rays_d"] = d
    out, _ = run(inputs, "warp")
    expect = (inputs["a"] * out.weight_sum)[:, None].expand_as(out.rendered)
    assert torch.allclose(out.rendered, expect, atol=1e-6)
    assert torch.allclose(out.surface_rendered, inputs["a"][:, None].expand_as(out.surface_rendered))


def test_sampling_ops_match_twin(device):
    g = torch.Generator().manual_seed(5)
    R = 40
    pix = (torch.rand(R, 2, generator=g) * torch.tensor([CAM.width - 1.0, CAM.height - 1.0])).to(device)
    ow, dw, nw, fw = ops.camera_rays(pix, CAM, (500.0, 900.0))
    ot, dt, nt, ft = ops.camera_rays(pix.double(), CAM, (500.0, 900.0), backend="torch")
    assert_close(dw, dt, atol=1e-6, what="rays")
    assert_close(nw, nt, rtol=1e-6, atol=1e-4, what="near")
    jit = (torch.rand(R, generator=g) - 0.5).to(device)
    zw = ops.stratified_samples(nw, fw, 32, jit)
    zt = ops.stratified_samples(nw, fw, 32, jit, backend="torch")
    assert_close(zw, zt, rtol=1e-6, atol=1e-4, what="stratified")
    assert (zw[:, 1:] > zw[:, :-1]).all() and (zw >= nw[:, None]).all() and (zw <= fw[:, None]).all()
    # an SDF with a surface at depth ~700: up-sampling concentrates samples there
    t_surf = 700.0 / dw[:, 2]
    sdf = t_surf[:, None] - zw
    for inv_s, share in ((0.08, 0.6), (0.64, 0.9)):
        uw = ops.upsample_samples(zw, sdf, ow, dw, 16, inv_s)
        ut = ops.upsample_samples(zw, sdf, ow, dw, 16, inv_s, backend="torch")
        assert_close(uw, ut, rtol=1e-5, atol=2e-3, what=f"upsample {inv_s}")
        assert (uw[:, 1:] >= uw[:, :-1]).all()
        near_surface = ((uw - t_surf[:, None]).abs() < 25.0).float().mean()
        assert near_surface > share  # sharper inv_s: more samples near the surface
    zn = ops.upsample_samples(zw, sdf, ow, dw, 16, 0.64)
    mz, mf = ops.merge_samples(zw, sdf, zn, t_surf[:, None] - zn)
    mzt, mft = ops.merge_samples(zw, sdf, zn, t_surf[:, None] - zn, backend="torch")
    assert torch.equal(mz, mzt) and torch.allclose(mf, mft)
    assert (mz[:, 1:] >= mz[:, :-1]).all()


def test_render_under_torch_compile_has_no_graph_break():
    inputs = make_inputs(R=16, S=8, N=2)

    def f(sdf, grad, inv_s):
        out = ops.render_structured_light(sdf, grad, inputs["z_vals"], inputs["rays_o"], inputs["rays_d"], inputs["a"],
                                          inputs["b"], inputs["patterns"], PROJ, inv_s)
        return (out.rendered - 0.3).abs().mean() + out.eikonal.mean()

    args = (inputs["sdf"].requires_grad_(), inputs["sdf_grad"].requires_grad_(), inputs["inv_s"].requires_grad_())
    compiled = torch.compile(f, fullgraph=True, backend="aot_eager")
    loss_c = compiled(*args)
    loss_e = f(*args)
    assert torch.allclose(loss_c, loss_e)
    gc = torch.autograd.grad(loss_c, args)
    ge = torch.autograd.grad(f(*args), args)
    for x, y in zip(gc, ge):
        assert torch.allclose(x, y)


@pytest.mark.parametrize("used", [("rendered",), ("surface_rendered", "depth"), ("rendered", "surface_rendered", "eikonal"), ("rendered", "eikonal_sum")])
def test_backward_with_unused_outputs(device, used):
    """Outputs no loss uses get no cotangent: the Warp backward must skip them, not read garbage."""
    inputs = make_inputs(R=32, S=16, N=3, device=device, seed=11)
    grads = {}
    for backend in ("warp", "torch"):
        sdf = inputs["sdf"].clone().requires_grad_()
        grad = inputs["sdf_grad"].clone().requires_grad_()
        out = ops.render_structured_light(sdf, grad, inputs["z_vals"], inputs["rays_o"], inputs["rays_d"], inputs["a"],
                                          inputs["b"], inputs["patterns"], PROJ, inputs["inv_s"], backend=backend)
        loss = sum(getattr(out, f).float().pow(2).sum() for f in used)
        grads[backend] = torch.autograd.grad(loss, [sdf, grad])
    for w, t in zip(grads["warp"], grads["torch"]):
        assert_close(w, t, atol=3e-4 * max(t.abs().max().item(), 1.0), what=f"{used}")


def test_sample_major_layout_gives_the_same_result(device):
    """Kernels read any strides: sample-major inputs (the renderer's layout, coalesced on GPUs) and
    row-major inputs give identical results; outputs come back as [R, S] either way."""
    inputs = make_inputs(R=24, S=10, N=3, device=device, seed=13)
    ref_out, ref_grads = run(inputs, "warp")
    sm = dict(inputs)
    for k in ("sdf", "z_vals"):
        sm[k] = inputs[k].t().contiguous().t()
    sm["sdf_grad"] = inputs["sdf_grad"].transpose(0, 1).contiguous().transpose(0, 1)
    assert sm["sdf"].stride(0) == 1
    out, grads = run(sm, "warp")
    for f in FIELDS:
        assert torch.equal(getattr(out, f), getattr(ref_out, f)), f
    assert out.weights.stride(0) == 1  # outputs follow the input layout
    for g, r in zip(grads, ref_grads):
        assert torch.equal(g, r)
