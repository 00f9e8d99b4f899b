"""The NeuS field: its explicit gradient equals autograd's (values, gradients, and the parameter
gradients of an Eikonal loss on them), geometric initialisation, the variance, the frustum volume."""
import numpy as np
import pytest
import torch

from slwarp.neural.fields import LearnedVariance, NeuSField, Volume, sdf_and_gradient
from slwarp.sim.rigs import make_rig

VOL = Volume((-400.0, -300.0, 434.0), (400.0, 300.0, 1116.0))


def random_points(n, dtype=torch.float64, seed=0):
    g = torch.Generator().manual_seed(seed)
    lo, hi = torch.tensor(VOL.lo, dtype=dtype), torch.tensor(VOL.hi, dtype=dtype)
    return torch.rand(n, 3, generator=g, dtype=dtype) * (hi - lo) + lo


@pytest.mark.parametrize("kw", [dict(), dict(init="camera", far=1100.0), dict(hidden=32, layers=3, skip=None, n_freqs=0),
                                dict(hidden=48, layers=4, skip=2, n_freqs=4)])
def test_explicit_gradient_equals_autograd(kw):
    torch.manual_seed(0)
    f = NeuSField(VOL, **kw).double()
    with torch.no_grad():  # move away from the initialisation so every layer matters
        for p in f.parameters():
            p.add_(torch.randn_like(p) * 0.05)
    x = random_points(64).requires_grad_()
    val = f(x)
    (g_ref,) = torch.autograd.grad(val.sum(), x, create_graph=True)
    v2, g2 = f.value_and_gradient(x)
    torch.testing.assert_close(v2, val, rtol=1e-12, atol=1e-9)
    torch.testing.assert_close(g2, g_ref, rtol=1e-10, atol=1e-12)
    params = [p for p in f.parameters()]
    l_ref = ((g_ref.norm(dim=-1) - 1) ** 2).sum() + val.abs().sum()
    l_exp = ((g2.norm(dim=-1) - 1) ** 2).sum() + v2.abs().sum()
    a = torch.autograd.grad(l_ref, params, retain_graph=True, allow_unused=True)
    b = torch.autograd.grad(l_exp, params, allow_unused=True)
    for x_, y_ in zip(a, b):
        if x_ is not None:
            torch.testing.assert_close(y_, x_, rtol=1e-9, atol=1e-10)


def test_sdf_and_gradient_uses_autograd_for_other_modules():
    class Sphere(torch.nn.Module):
        def forward(self, x):
            return torch.linalg.norm(x - torch.tensor([0.0, 0.0, 700.0], dtype=x.dtype), dim=-1) - 100.0

    x = random_points(10)
    f, g = sdf_and_gradient(Sphere(), x)
    assert torch.allclose(g.norm(dim=-1), torch.ones(10, dtype=torch.float64))


def test_geometric_initialisation():
    torch.manual_seed(0)
    sphere = NeuSField(VOL)
    c = torch.tensor(VOL.center, dtype=torch.float32)
    assert sphere(c[None]).item() < 0 < sphere((c + torch.tensor([0, 0, 0.9 * VOL.scale]))[None]).item()
    cam = NeuSField(VOL, init="camera", far=1000.0)
    x = torch.tensor([[0.0, 0.0, 500.0], [0.0, 0.0, 1200.0]])
    f = cam(x)
    assert abs(f[0].item() - 500.0) < 1.0 and abs(f[1].item() + 200.0) < 1.0
    _, g = cam.value_and_gradient(x)
    assert torch.allclose(g.norm(dim=-1), torch.ones(2), atol=1e-2)


def test_variance_and_volume():
    v = LearnedVariance(0.3, length_scale=400.0)
    assert v().item() == pytest.approx(np.exp(3.0) / 400.0, rel=1e-6)
    cam, _ = make_rig("small")
    valid = np.zeros((cam.height, cam.width), bool)
    valid[50:200, 40:300] = True
    vol = Volume.from_frustum(cam, valid, (500.0, 1000.0))
    d = cam.pixel_to_ray(np.array([[40.0, 50.0], [299.0, 199.0]]))
    for z in (500.0, 1000.0):
        p = d / d[:, 2:3] * z
        assert np.all(p >= np.array(vol.lo) - 1e-6) and np.all(p <= np.array(vol.hi) + 1e-6)
    assert vol.lo[2] < 500.0 and vol.hi[2] > 1000.0
