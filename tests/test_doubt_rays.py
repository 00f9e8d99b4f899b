"""Rays drawn more often where the start doubts (sampling.doubt_rays): the renderer's emphasised draw list, the doubtful
pixels, and a training run with them on the CPU."""
import numpy as np
import pytest
import torch

from slwarp.neural.config import preset
from slwarp.neural.render import StructuredLightRenderer
from slwarp.neural.start import doubtful_pixels
from slwarp.neural.training import Trainer
from slwarp.sim.simulate import SimOptions, simulate_scene


@pytest.fixture(scope="module")
def small_scan():
    return simulate_scene("rods", "random6", rig="small", options=SimOptions(seed=1))


def _renderer(scan):
    field = torch.nn.Linear(3, 1)  # the draws never evaluate the field
    return StructuredLightRenderer(field, scan.camera, scan.projector, scan.patterns, scan.images,
                                   depth_range=scan.depth_range, device="cpu")


def test_emphasised_pixels_get_their_share_of_the_draws(small_scan):
    r = _renderer(small_scan)
    assert r.n_draw == r.n_valid
    valid = r.valid_map.numpy()
    H, W = valid.shape
    chosen = np.zeros((H, W), bool)
    chosen[:, : W // 8] = True  # a strip: about an eighth of the valid pixels
    m = int((chosen & valid).sum())
    assert r.emphasise(chosen, 0.5) == m
    g = torch.Generator().manual_seed(0)
    index = r.valid_batch(r.draw_valid(200_000, g, emphasised=True)).index.numpy()
    assert valid.reshape(-1)[index].all()  # only valid pixels, emphasised or not
    inside = chosen.reshape(-1)[index].mean()
    expected = 0.5 + 0.5 * m / r.n_valid  # the extra list's share, and the strip's part of the uniform rest
    assert abs(inside - expected) < 0.01
    # without emphasis the strip gets its area's share
    r.emphasise(None, 0.5)
    assert r.n_draw == r.n_valid
    inside = chosen.reshape(-1)[r.valid_batch(r.draw_valid(200_000, g, emphasised=True)).index.numpy()].mean()
    assert abs(inside - m / r.n_valid) < 0.01


def test_the_emphasis_outlives_new_frames_and_refuses_bad_input(small_scan):
    r = _renderer(small_scan)
    chosen = np.zeros((small_scan.camera.height, small_scan.camera.width), bool)
    chosen[::7, ::5] = True
    r.emphasise(chosen, 0.25)
    n_draw = r.n_draw
    assert n_draw == r.n_valid + round(0.25 / 0.75 * r.n_valid)
    r.set_frames(small_scan.images, small_scan.patterns)
    assert r.n_draw == n_draw
    with pytest.raises(ValueError, match="share"):
        r.emphasise(chosen, 1.0)
    with pytest.raises(ValueError, match="camera is"):
        r.emphasise(chosen[1:], 0.25)
    # nothing valid chosen: uniform
    assert r.emphasise(np.zeros_like(chosen), 0.25) == 0 and r.n_draw == r.n_valid


def test_doubtful_pixels_are_lit_pixels_of_fair_modulation_without_a_confirmed_depth_and_their_neighbours():
    lit = torch.ones(6, 7, dtype=torch.bool)
    lit[:, 0] = False
    modulation = torch.full((6, 7), 0.4)
    confirmed = torch.full((6, 7), 500.0)
    confirmed[2, 3] = float("nan")
    confirmed[5, 0] = float("nan")  # unlit: never doubtful, nor spreading doubt
    confirmed[5, 6] = float("nan")
    modulation[5, 6] = 0.1  # dark: its doubt is noise, not geometry
    alone = doubtful_pixels(confirmed, lit, modulation, 0)
    assert alone.sum() == 1 and alone[2, 3]
    spread = doubtful_pixels(confirmed, lit, modulation, 1)
    expected = torch.zeros(6, 7, dtype=torch.bool)
    expected[1:4, 2:5] = True
    assert torch.equal(spread, expected)
    assert doubtful_pixels(confirmed, torch.zeros_like(lit), modulation, 1).sum() == 0


def test_a_run_with_doubt_rays_draws_from_the_doubtful_pixels_and_trains(small_scan):
    cfg = preset("tiny", device="cpu", iters=30, init_iters=10, doubt_rays=0.3, doubt_rays_radius=1,
                 doubt_rays_until=0.5, surface_weight=1.0)
    t = Trainer(small_scan, cfg, progress=False)
    assert t.surface_depth is not None
    assert 0 < t.doubt_pixels < t.renderer.n_valid
    assert t.renderer.n_draw == t.renderer.n_valid + round(0.3 / 0.7 * t.renderer.n_valid)
    history = t.train()
    assert np.isfinite(history.loss[-1])
    # the first half of the 40 iterations draws from the whole list, the rest from the valid pixels alone
    assert t._doubt_until == 20
    g = torch.Generator().manual_seed(0)
    assert t._draw(g, emphasised=True)[0].max() >= t.renderer.n_valid
    assert t._draw(g, emphasised=False)[0].max() < t.renderer.n_valid


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a CUDA device")
def test_the_captured_step_serves_both_phases_of_the_doubt_rays(small_scan):
    """With a CUDA graph the draws are made ahead and gathered from the same list in both phases: the captured run
    gives the plain launches' losses across doubt_rays_until, and draws from the emphasis only before it."""
    runs = {}
    for graph in (False, True):
        cfg = preset("tiny", device="cuda", cuda_graph=graph, compile=False, iters=20, init_iters=6, doubt_rays=0.5,
                     doubt_rays_until=0.5, surface_weight=1.0)
        t = Trainer(small_scan, cfg, progress=False)
        assert t.doubt_pixels > 0
        runs[graph] = (np.array([float(t.step()["loss"]) for _ in range(26)]), t)
    assert runs[True][1].graph_captured, "the step was not captured"
    np.testing.assert_allclose(runs[True][0], runs[False][0], rtol=2e-4, atol=1e-6)
