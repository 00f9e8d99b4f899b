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
import warp as wp

from slwarp.kernels.geometry import TRANS_EPS
from slwarp.kernels.sampling import CDF_EPS, PDF_EPS, upsample_inverse_cdf, upsample_place
from slwarp.neural import ops
from slwarp.neural.ops import launch, twin
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


def run(inputs, backend, seed=1, overwrite=None, **kw):
    """The render's outputs and the gradients (sdf, sdf_grad, inv_s) of a random weighting of them; overwrite: a dict
    of input tensors to overwrite with garbage between the forward and the backward."""
    sdf = inputs["sdf"].clone().requires_grad_()
    grad = inputs["sdf_grad"].clone().requires_grad_()
    inv_s = inputs["inv_s"].clone().requires_grad_()
    args = {**inputs, "sdf": sdf, "sdf_grad": grad, "inv_s": inv_s}
    out = ops.render_structured_light(**{k: args[k] for k in ["sdf", "sdf_grad", "z_vals", "rays_o", "rays_d", "a", "b", "patterns"]},
                                      projector=PROJ, inv_s=inv_s, backend=backend, **kw)
    for t in (overwrite or {}).values():
        t.fill_(float("nan"))
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
    bounds = launch.bounds_list([[-300.0, -300.0, 550.0], [300.0, 300.0, 850.0]])

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
    for name, w, t in zip(("d sdf", "d sdf_grad", "d inv_s"), gw, gt):
        assert_close(w, t, rtol=1e-3, atol=1e-4, what=f"{case} {name}")
    if case == "zero_weights":
        assert ow.weight_sum.abs().max() < 1e-3
    if case == "leaves_projector":  # rays out of the projector's view or turned backwards see no pattern: a x weights
        unlit = (inputs["a"] * ow.weight_sum).unsqueeze(1).expand_as(ow.rendered)
        assert torch.allclose(ow.rendered.cpu(), unlit.cpu(), atol=1e-5)


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


def sequential_merge(z_a, f_a, z_b, f_b):
    """The textbook stable merge, row by row in Python (a before b on ties): the merge's reference."""
    zs, fs = [], []
    for za, fa, zb, fb in zip(z_a.tolist(), f_a.tolist(), z_b.tolist(), f_b.tolist()):
        i = j = 0
        z, f = [], []
        while i < len(za) or j < len(zb):
            if j >= len(zb) or (i < len(za) and za[i] <= zb[j]):
                z.append(za[i]), f.append(fa[i])
                i += 1
            else:
                z.append(zb[j]), f.append(fb[j])
                j += 1
        zs.append(z), fs.append(f)
    return torch.tensor(zs, dtype=torch.float32).reshape(len(zs), -1), torch.tensor(fs, dtype=torch.float32).reshape(len(zs), -1)


@pytest.mark.parametrize("na,nb", [(7, 4), (3, 11), (16, 16), (1, 5), (6, 0)])
def test_merge_samples_is_stable_and_exact(device, na, nb):
    """Ties between a and b and within each list: a's elements come first, each list keeps its order. The values f
    tag every element (a_k: k, b_j: 100 + j), so any other order of equal distances shows."""
    g = torch.Generator().manual_seed(na * 31 + nb)
    R = 9
    z_a = torch.sort(torch.randint(0, 6, (R, na), generator=g).float(), dim=1).values
    z_b = torch.sort(torch.randint(0, 6, (R, nb), generator=g).float(), dim=1).values
    z_a[0] = 2.0  # a row of one repeated value in a ...
    z_b[0] = 2.0  # ... tied with all of b
    z_b[1] = -1.0  # b entirely before a
    z_b[2] = 10.0  # b entirely after a
    f_a = torch.arange(na, dtype=torch.float32).expand(R, na).contiguous()
    f_b = (100.0 + torch.arange(nb, dtype=torch.float32)).expand(R, nb).contiguous()
    dev = lambda t: t.to(device)  # noqa: E731
    z, f = ops.merge_samples(dev(z_a), dev(f_a), dev(z_b), dev(f_b))
    assert z.shape == (R, na + nb) and f.shape == (R, na + nb)
    zs, fs = sequential_merge(z_a, f_a, z_b, f_b)
    zt, ft = ops.merge_samples(z_a, f_a, z_b, f_b, backend="torch")
    assert torch.equal(z.cpu(), zs) and torch.equal(f.cpu(), fs)
    assert torch.equal(z.cpu(), zt) and torch.equal(f.cpu(), ft)
    if nb:
        assert f[0].tolist() == list(range(na)) + [100.0 + j for j in range(nb)]  # all tied: a first, in order


def upsample_rays(R, S, device, seed=0):
    """Rays of the small rig with stratified samples and an SDF crossing zero near 700 mm (random depth per ray);
    ray 0 has no surface (the SDF stays far positive: every weight ~PDF_EPS, a straight CDF); ray 1 reaches the
    surface at its first samples; rays 2-3 point out of the bounds used below for most of their length."""
    g = torch.Generator().manual_seed(seed)
    pix = torch.rand(R, 2, generator=g) * torch.tensor([CAM.width - 1.0, CAM.height - 1.0])
    o, d, near, far = ops.camera_rays(pix, CAM, (500.0, 900.0), backend="torch")
    z = ops.stratified_samples(near, far, S, torch.rand(R, generator=g) - 0.5, backend="torch")
    t_surf = 700.0 / d[:, 2] + torch.randn(R, generator=g) * 50
    t_surf[1] = z[1, min(1, S - 1)]
    sdf = t_surf[:, None] - z + torch.randn(R, S, generator=g) * 0.3
    sdf[0] = 200.0 + torch.rand(S, generator=g)
    d[2:4] = torch.nn.functional.normalize(d[2:4] + torch.tensor([0.6, 0.0, 0.0]), dim=1)
    return [t.to(device) for t in (z, sdf, o, d)]


@pytest.mark.parametrize("S,n_new", [(12, 9), (17, 32)])
def test_upsample_matches_twin_on_edge_rays(device, S, n_new):
    z, sdf, o, d = upsample_rays(10, S, device, seed=S)
    bounds = [[-200.0, -200.0, 550.0], [200.0, 200.0, 850.0]]
    for inv_s in (0.05, 0.64, 8.0):
        for bnd in (None, bounds):
            zw = ops.upsample_samples(z, sdf, o, d, n_new, inv_s, bounds=bnd)
            zt = ops.upsample_samples(z, sdf, o, d, n_new, inv_s, bounds=bnd, backend="torch")
            assert zw.shape == (10, n_new)
            assert_close(zw, zt, rtol=1e-5, atol=2e-3, what=f"upsample S={S} inv_s={inv_s} bounds={bnd is not None}")
            assert (zw[:, 1:] >= zw[:, :-1]).all()
            assert ((zw >= z[:, :1]) & (zw <= z[:, -1:])).all()
    # the ray without a surface: equal weights, so the new samples spread evenly between the first and last sample
    zw = ops.upsample_samples(z, sdf, o, d, n_new, 0.64)
    u = (torch.arange(n_new, dtype=torch.float64) + 0.5) / n_new
    even = z[0, 0].double().cpu() + u * (z[0, -1] - z[0, 0]).double().cpu()
    assert_close(zw[0].double(), even, rtol=0, atol=0.05 * float(z[0, 1] - z[0, 0]), what="no-surface ray")


def test_upsample_of_a_single_sample(device):
    """One sample per ray: no interval, an empty CDF beyond 0, so every new sample sits on the sample (the twin
    needs two samples)."""
    z, sdf, o, d = upsample_rays(6, 1, device, seed=1)
    zw = ops.upsample_samples(z, sdf, o, d, 5, 0.64)
    assert torch.equal(zw, z.expand(-1, 5))


@wp.kernel
def inverse_cdf_with_total(z: wp.array2d(dtype=float), alpha: wp.array2d(dtype=float), total: wp.array(dtype=float),
                           z_new: wp.array2d(dtype=float)):
    """The up-sampling placement with a given normaliser per ray (the op uses the weights' sum)."""
    r, j = wp.tid()
    z_new[r, j] = upsample_inverse_cdf(z, alpha, r, total[r], (float(j) + 0.5) / float(z_new.shape[1]))


def inverse_cdf_reference(z, alpha, total, n):
    """The per-ray walk in float64: CDF of w_i = alpha_i T_i + PDF_EPS over total, the first CDF value above u_j,
    CDF_EPS and beyond-the-end rules as in twin.upsample_samples."""
    out = []
    for zr, ar, tot in zip(z.tolist(), alpha.tolist(), total.tolist()):
        cdf, trans = [0.0], 1.0
        for a in ar:
            cdf.append(cdf[-1] + (a * trans + PDF_EPS) / tot)
            trans *= 1.0 - a + TRANS_EPS
        row = []
        for j in range(n):
            u = (j + 0.5) / n
            k = next((k for k in range(1, len(cdf)) if cdf[k] > u), None)
            if k is None:
                row.append(zr[-1])
                continue
            denom = cdf[k] - cdf[k - 1]
            row.append(zr[k - 1] + (u - cdf[k - 1]) / (denom if denom >= CDF_EPS else 1.0) * (zr[k] - zr[k - 1]))
        out.append(row)
    return torch.tensor(out, dtype=torch.float64)


def test_upsample_placement_follows_the_cdf_rules(device):
    """The placement on hand-made weights and normalisers, against the walk in float64: quantiles beyond a last
    CDF value below 1 sit on the last sample, and one in an interval the CDF rises over by less than CDF_EPS sits
    at the interval's start. Five intervals: one unrolled block of four and the remainder."""
    z = torch.tensor([[0.0, 1.0, 3.0, 4.0, 7.0, 9.0]]) + torch.tensor([[0.0], [10.0], [20.0]])
    alpha = torch.tensor([[0.0, 0.0, 0.0, 0.0, 0.0],  # equal weights
                          [0.9999, 0.0, 0.0, 0.0, 0.0],  # all weight in interval 0, then flat intervals
                          [0.05, 0.3, 0.9, 0.2, 0.1]])
    trans = torch.cat([torch.ones(3, 1, dtype=torch.float64), torch.cumprod(1.0 - alpha.double() + TRANS_EPS, 1)[:, :-1]], 1)
    w = alpha.double() * trans + PDF_EPS
    # row 0: the CDF ends at 0.8 (quantiles 13/16 and 15/16 beyond it); row 1: u = 15/16 lies 4e-6 into
    # flat interval 1 (it rises by PDF_EPS / total < CDF_EPS); row 2: the weights' own sum
    total = torch.stack([w[0].sum() * 1.25, w[1, 0] / (0.9375 - 4e-6), w[2].sum()])
    n_new = 8
    zd, ad, td = z.to(device), alpha.to(device), total.float().to(device)
    z_new = torch.empty(3, n_new, device=device)
    launch.launch(inverse_cdf_with_total, (3, n_new), [launch.desc(zd), launch.desc(ad), launch.desc(td),
                                                       launch.desc(z_new)], zd.device)
    ref = inverse_cdf_reference(z.double(), alpha.double(), total, n_new)
    assert_close(z_new.double(), ref, rtol=0, atol=1e-4, what="placement")
    assert z_new[0, -2:].tolist() == [9.0, 9.0] and z_new[0, -3].item() < 9.0
    assert 0 < z_new[1, -1].item() - 11.0 < 1e-4 and z_new[1, -2].item() < 11.0
    # and through the op's kernel (total = the weights' sum): the same walk
    z_op = torch.empty(3, n_new, device=device)
    launch.launch(upsample_place, (3, n_new), [launch.desc(zd), launch.desc(ad), launch.desc(z_op)], zd.device)
    assert_close(z_op.double(), inverse_cdf_reference(z.double(), alpha.double(), w.sum(1), n_new), rtol=0, atol=1e-4,
                 what="upsample_place")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_sampling_ops_capture_in_a_cuda_graph(capture_cuda_graph):
    """Up-sampling and merge in one CUDA graph (scratch allocated inside it, no host synchronisation): the
    replay gives the eager result, also for new inputs copied into the captured tensors."""
    z, sdf, o, d = upsample_rays(64, 24, "cuda")

    def step():
        z_new = ops.upsample_samples(z, sdf, o, d, 16, 0.64)
        return ops.merge_samples(z, sdf, z_new, z_new * 0.5)

    graph, out = capture_cuda_graph(step)
    z2, sdf2, _, _ = upsample_rays(64, 24, "cuda", seed=5)
    for dst, src in ((z, z2), (sdf, sdf2)):
        dst.copy_(src)
    graph.replay()
    torch.cuda.synchronize()
    for a, b in zip(out, step()):
        assert torch.equal(a, b)


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


def test_backward_reads_the_copies_that_saved_tensor_hooks_return(device):
    """The eager backward reuses the forward's kernel arguments only while the saved inputs are the same memory:
    saved-tensor hooks (offloading) may return copies, and the forward's memory may change meanwhile."""
    inputs = make_inputs(R=16, S=8, N=3, device=device, seed=17)
    ref_out, ref_grads = run(inputs, "warp")
    moved = {k: v.clone() for k, v in inputs.items()}
    with torch.autograd.graph.saved_tensors_hooks(lambda t: t.clone(), lambda t: t):
        out, grads = run(moved, "warp", overwrite=moved)
    for f in FIELDS:
        assert torch.equal(getattr(out, f), getattr(ref_out, f)), f
    for g, r in zip(grads, ref_grads):
        assert torch.equal(g, r)
