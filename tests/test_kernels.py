"""The shared Warp helpers (slwarp.kernels.geometry) against numpy references: the bilinear taps of one
channel and of N packed patterns, the gradient of the pattern taps, torch tensors passed to kernels
through array descriptors (any strides, vector elements), and struct arguments filled from torch tensors
through a cached launch whose parameters are rewritten from call to call."""
import numpy as np
import pytest
import torch
import warp as wp

from slwarp.devices import warp_device
from slwarp.kernels import runtime
from slwarp.kernels.geometry import bilinear_channel, pattern_sampler

N = 3
vecN, sample_all, sample_all_grad = pattern_sampler(N)


@wp.kernel
def _channel_kernel(img: wp.array3d(dtype=float), uv: wp.array(dtype=wp.vec2), c: int, out: wp.array(dtype=float)):
    i = wp.tid()
    out[i] = bilinear_channel(img, c, uv[i][0], uv[i][1])


@wp.kernel
def _patterns_kernel(pat: wp.array3d(dtype=float), uvo: wp.array(dtype=wp.vec3), cot: wp.array2d(dtype=float),
                     values: wp.array2d(dtype=float), grad: wp.array(dtype=wp.vec2)):
    i = wp.tid()
    v = sample_all(pat, uvo[i])
    c = vecN()
    for n in range(N):
        values[i, n] = v[n]
        c[n] = cot[i, n]
    grad[i] = sample_all_grad(pat, uvo[i], c)


@wp.struct
class _Inputs:
    x: wp.array2d(dtype=wp.vec3)
    w: wp.array(dtype=float)  # read only where use_w
    use_w: int
    scale: float
    offset: wp.vec3


@wp.kernel
def _weighted_sum(inp: _Inputs, out: wp.array(dtype=float)):
    r = wp.tid()
    acc = float(0.0)
    for k in range(inp.x.shape[1]):
        acc += wp.dot(inp.x[r, k] + inp.offset, wp.vec3(1.0, 10.0, 100.0))
    if inp.use_w != 0:
        acc *= inp.w[r]
    out[r] = acc * inp.scale


@wp.kernel
def _sum_vec3(x: wp.array2d(dtype=wp.vec3), out: wp.array(dtype=float)):
    r = wp.tid()
    acc = float(0.0)
    for k in range(x.shape[1]):
        acc += wp.dot(x[r, k], wp.vec3(1.0, 10.0, 100.0))
    out[r] = acc


def bilinear_reference(img: np.ndarray, u: float, v: float) -> float:
    """Bilinear value of img [H, W] at (u, v), pixel centres at integers, zero outside."""
    H, W = img.shape
    u0, v0 = int(np.floor(u)), int(np.floor(v))
    fu, fv = u - u0, v - v0
    acc = 0.0
    for dy, wy in ((0, 1 - fv), (1, fv)):
        for dx, wx in ((0, 1 - fu), (1, fu)):
            x, y = u0 + dx, v0 + dy
            if 0 <= x < W and 0 <= y < H:
                acc += wx * wy * img[y, x]
    return acc


def random_positions(rng, W, H, n):
    # inside, across the border and far outside; fractions away from 0 and 1 so finite differences stay in a cell
    u = np.floor(rng.uniform(-3, W + 2, n)) + rng.uniform(0.1, 0.9, n)
    v = np.floor(rng.uniform(-3, H + 2, n)) + rng.uniform(0.1, 0.9, n)
    return np.stack([u, v], -1).astype(np.float32)


def test_bilinear_channel_matches_reference():
    runtime.init()
    rng = np.random.default_rng(0)
    img = rng.random((2, 7, 9)).astype(np.float32)
    uv = random_positions(rng, 9, 7, 200)
    out = wp.empty(200, dtype=float, device="cpu")
    wp.launch(_channel_kernel, dim=200, inputs=[wp.array(img, device="cpu"), wp.array(uv, dtype=wp.vec2, device="cpu"), 1],
              outputs=[out], device="cpu")
    ref = [bilinear_reference(img[1], float(u), float(v)) for u, v in uv]
    np.testing.assert_allclose(out.numpy(), ref, atol=1e-6)


def test_pattern_taps_and_their_gradient_match_reference():
    runtime.init()
    rng = np.random.default_rng(1)
    pats = rng.random((N, 6, 8)).astype(np.float32)  # [N, H, W]
    uv = random_positions(rng, 8, 6, 150)
    ok = (rng.random(150) > 0.2).astype(np.float32)
    uvo = np.concatenate([uv, ok[:, None]], -1)
    cot = rng.normal(size=(150, N)).astype(np.float32)
    values = wp.empty((150, N), dtype=float, device="cpu")
    grad = wp.empty(150, dtype=wp.vec2, device="cpu")
    wp.launch(_patterns_kernel, dim=150, inputs=[wp.array(np.ascontiguousarray(pats.transpose(1, 2, 0)), device="cpu"),
              wp.array(uvo, dtype=wp.vec3, device="cpu"), wp.array(cot, device="cpu")], outputs=[values, grad], device="cpu")

    def weighted(u, v, i):
        return sum(cot[i, n] * bilinear_reference(pats[n].astype(np.float64), u, v) for n in range(N))

    h = 1e-4
    for i, (u, v) in enumerate(uv.astype(np.float64)):
        ref = [bilinear_reference(pats[n], u, v) * ok[i] for n in range(N)]
        np.testing.assert_allclose(values.numpy()[i], ref, atol=1e-6)
        g_ref = [(weighted(u + h, v, i) - weighted(u - h, v, i)) / (2 * h), (weighted(u, v + h, i) - weighted(u, v - h, i)) / (2 * h)]
        np.testing.assert_allclose(grad.numpy()[i], np.asarray(g_ref) * ok[i], atol=1e-4)


@pytest.mark.parametrize("layout", ["row-major", "sample-major"])
def test_array_descriptors_carry_strides_and_vector_elements(device, layout):
    g = torch.Generator().manual_seed(2)
    x = torch.randn(5, 4, 3, generator=g)
    if layout == "sample-major":
        x = x.transpose(0, 1).contiguous().transpose(0, 1)  # sample-major [R, S, 3]: consecutive rays adjacent
        assert x.stride(0) == 3
    x = x.to(device)
    out = torch.empty(5, device=device)
    wp_ = runtime.init()
    if x.device.type == "cuda":
        torch.cuda.synchronize()  # Warp launches on its own stream here: torch's copy must be done
    wp_.launch(_sum_vec3, dim=5, inputs=[runtime.array_desc(x, 3), runtime.array_desc(out)], device=warp_device(x.device))
    if x.device.type == "cuda":
        wp_.synchronize_device(warp_device(x.device))
    ref = (x.double() * torch.tensor([1.0, 10.0, 100.0], dtype=torch.float64, device=device)).sum((1, 2))
    torch.testing.assert_close(out.double(), ref, rtol=1e-5, atol=1e-4)


def test_cached_launch_rewrites_struct_arguments(device):
    """One recorded launch, replayed with other tensors (other shapes, strides and devices' pointers), other
    numbers and a null array that the kernel does not read: each call reads its own arguments."""
    wp_ = runtime.init()
    launcher = runtime.CachedLaunch(_weighted_sum, block_dim=64)
    g = torch.Generator().manual_seed(3)
    dev = warp_device(torch.device(device))
    for R, S, use_w, scale in [(5, 4, True, 1.0), (7, 2, False, -2.0), (3, 6, True, 0.5)]:
        x = torch.randn(S, R, 3, generator=g).to(device).transpose(0, 1)  # sample-major [R, S, 3]
        w = torch.rand(R, generator=g).to(device)
        offset = (float(R), 0.5, -1.0)
        out = torch.full((R,), float("nan"), device=device)
        inp = runtime.struct_value(_Inputs, x=x, w=w if use_w else None, use_w=int(use_w), scale=scale,
                                   offset=wp_.vec3(*offset))
        if x.device.type == "cuda":
            torch.cuda.synchronize()  # Warp launches on its own stream here: torch's copies must be done
        launcher(R, [inp, runtime.array_desc(out)], dev)
        if x.device.type == "cuda":
            wp_.synchronize_device(dev)
        ref = ((x.double() + torch.tensor(offset, dtype=torch.float64, device=device))
               * torch.tensor([1.0, 10.0, 100.0], dtype=torch.float64, device=device)).sum((1, 2))
        ref = ref * (w.double() if use_w else 1.0) * scale
        torch.testing.assert_close(out.double(), ref, rtol=1e-5, atol=1e-4)
