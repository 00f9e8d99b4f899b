"""Pattern design (slwarp.design, `slwarp design-patterns`): the objective's gradient through the Warp reprojection
matches its torch twin, a short descent lowers the objective, binary output keeps every pixel's code, and a designed
set written by the command is read back and projected by `slwarp simulate --patterns`."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from slwarp.cli import main as cli_main
from slwarp.design import CodeModel, DesignOptions, NoiseModel, binarise, code_image, design_patterns, miss_loss
from slwarp.design.optimise import normalised_codes
from slwarp.scans.pattern_files import read_pattern_set
from slwarp.sim.rigs import DEPTH_RANGE_MM, make_rig

CAMERA, PROJECTOR = make_rig("small")


@pytest.fixture(scope="module")
def model():
    return CodeModel(CAMERA, PROJECTOR, DEPTH_RANGE_MM, NoiseModel())


def test_hypotheses_follow_the_epipolar_line(model):
    # hypotheses every 0.5 px or less along the longest line; the direction is a unit vector
    assert model.hypotheses >= model.span_px / 0.5
    assert np.isclose(np.linalg.norm(model.direction), 1.0)
    g = torch.Generator()
    g.manual_seed(0)
    b = model.batch(64, 3, g)
    # the hypothesis nearest the truth is within one hypothesis spacing (0.5 px) of it, on every pixel
    assert float(b.dist.min(1).values.max()) <= 0.5 + 1e-3
    # the true pixels are on the projector image (unlit ones were dropped)
    assert bool(((b.uv_true[:, 0, 0] > -0.5) & (b.uv_true[:, 0, 0] < PROJECTOR.width - 0.5)).all())


def _assert_warp_matches_twin(model, batch, theta):
    """The objective and its gradient in theta, through the Warp reprojection and through its torch twin, agree."""
    grads, losses = [], []
    for backend in ("warp", "torch"):
        th = theta.clone().requires_grad_(True)
        loss = miss_loss(code_image(normalised_codes(th), model.coords), batch, model.noise, backend=backend)
        loss.backward()
        grads.append(th.grad)
        losses.append(float(loss.detach()))
    assert losses[0] == pytest.approx(losses[1], rel=1e-4)
    assert float(grads[1].abs().max()) > 0
    assert torch.allclose(grads[0], grads[1], rtol=1e-3, atol=1e-3 * float(grads[1].abs().max()))


def test_objective_gradient_warp_matches_twin(model):
    g = torch.Generator()
    g.manual_seed(1)
    batch = model.batch(96, 3, g)
    _assert_warp_matches_twin(model, batch, torch.randn(3, model.code_length, generator=g))


def test_a_window_batch_holds_each_pixels_neighbours_at_its_depth(model):
    """window 1: each pixel with its 3 x 3 camera neighbours; the centre is the pixel a window-0 batch of the same
    draws holds, with the same hypotheses, and the neighbours' true points lie on the centre's depth (their
    projector pixels a few px from the centre's)."""
    g0, g1 = torch.Generator(), torch.Generator()
    g0.manual_seed(4)
    g1.manual_seed(4)
    alone, win = model.batch(48, 3, g0), model.batch(48, 3, g1, window=1)
    M, Hn = alone.dist.shape
    assert win.uv_true.shape == (M, 9, 2) and win.uv_hyp.shape == (M, 9, Hn, 2) and win.lit.shape == (M, 9)
    assert win.noise.shape == (M, 9, 3) and win.lit[:, 4].all()
    assert torch.allclose(win.uv_true[:, 4], alone.uv_true[:, 0]) and torch.allclose(win.dist, alone.dist)
    assert torch.allclose(win.uv_hyp[:, 4], alone.uv_hyp[:, 0])
    step = torch.linalg.norm(win.uv_true - win.uv_true[:, 4:5], dim=-1)[win.lit]
    assert float(step.max()) < 4.0 and float(step.max()) > 0.5  # one camera px is a projector px or two
    # window_step 2: the same 3 x 3 pixels, twice as far apart
    g2 = torch.Generator()
    g2.manual_seed(4)
    wide = model.batch(48, 3, g2, window=1, step=2)
    assert torch.allclose(wide.uv_true[:, 4], win.uv_true[:, 4]) and torch.allclose(wide.dist, win.dist)
    ok = wide.lit & win.lit
    ratio = (torch.linalg.norm(wide.uv_true - wide.uv_true[:, 4:5], dim=-1)[ok]
             / torch.linalg.norm(win.uv_true - win.uv_true[:, 4:5], dim=-1)[ok].clamp_min(1e-9))
    ratio = ratio[torch.linalg.norm(win.uv_true - win.uv_true[:, 4:5], dim=-1)[ok] > 0]
    assert 1.9 < float(ratio.median()) < 2.1  # nearly linear over a few pixels (but where the image's edge clamps)


def test_windowed_objective_gradient_warp_matches_twin_and_sees_more(model):
    """With windows the Warp reprojection's gradient matches its twin's; and a window tells depths apart that a
    pixel's 3 values alone confuse: the same smooth random codes miss less."""
    g = torch.Generator()
    g.manual_seed(5)
    batch = model.batch(48, 3, g, window=1)
    _assert_warp_matches_twin(model, batch, torch.randn(3, model.code_length, generator=g))
    from slwarp.design.optimise import _smooth_start

    g.manual_seed(6)
    pats = code_image(normalised_codes(_smooth_start(3, model.code_length, 3.0, g, "cpu")), model.coords)
    rates = []
    for window in (0, 2):
        g.manual_seed(7)
        b = model.batch(2048 // (2 * window + 1) ** 2, 3, g, window=window)
        rates.append(miss_loss(pats, b, model.noise, backend="torch", details=True)[1]["miss_rate"])
    assert rates[1] < 0.5 * rates[0], rates


def test_the_camera_blur_is_scored_over_its_spread(model):
    """The observations come from the patterns at the camera's blur (`observed`), the hypotheses' codes at the modelled
    one: the same blur gives the loss without `observed`; a one-pixel detail that the code hangs on is a miss once the
    camera blurs it otherwise, while smooth codes barely notice."""
    from slwarp.neural.pattern_model import blur_patterns

    assert NoiseModel(blur_px=1.0, blur_spread=2.0).observed_blurs() == (0.5, 1.0, 2.0)
    assert NoiseModel(blur_px=1.0, blur_spread=1.0).observed_blurs() == (1.0,)
    assert NoiseModel(blur_px=1.0, blur_spread=2.0).observed_blurs(-1.0) == (0.5,)
    with pytest.raises(ValueError, match="spread"):
        NoiseModel(blur_spread=0.9)
    g = torch.Generator()
    g.manual_seed(5)
    batch = model.batch(1024, 4, g)
    H, W = PROJECTOR.height, PROJECTOR.width
    x = blur_patterns(torch.randn(4, 1, W, generator=g), 3.0)[:, 0]  # codes that vary over a few px, as a design starts
    x = (x - x.min(1, keepdim=True).values) / (x.max(1, keepdim=True).values - x.min(1, keepdim=True).values)
    smooth = x[:, None, :].expand(4, H, W).clone()
    spiky = smooth.clone()
    spiky[0, :, ::4], spiky[1, :, ::4], spiky[2, :, ::4] = 1.0, 0.0, 1.0  # every 4th column a detail one pixel wide

    def loss(p, sigma_obs):
        return float(miss_loss(blur_patterns(p, 1.0), batch, model.noise, backend="torch", observed=blur_patterns(p, sigma_obs)))

    assert loss(smooth, 1.0) == pytest.approx(float(miss_loss(blur_patterns(smooth, 1.0), batch, model.noise,
                                                              backend="torch")))

    def sensitivity(p):  # how far the loss moves when the camera's blur is half or twice the modelled one
        return abs(loss(p, 0.5) - loss(p, 1.0)) + abs(loss(p, 2.0) - loss(p, 1.0))

    assert sensitivity(spiky) > 3.0 * sensitivity(smooth)


def test_codes_span_zero_to_one_at_every_pixel():
    theta = torch.randn(4, 50)
    c = normalised_codes(theta)
    assert torch.allclose(c.min(0).values, torch.zeros(50)) and torch.allclose(c.max(0).values, torch.ones(50))
    b = binarise(np.random.default_rng(0).random((3, 5, 7)))
    assert set(np.unique(b)) <= {0.0, 1.0}
    assert (b.max(0) == 1).all() and (b.min(0) == 0).all()


def test_evaluate_patterns_takes_the_auto_backend(model):
    g = torch.Generator()
    g.manual_seed(2)
    batch = model.batch(64, 6, g)
    from slwarp.design import evaluate_patterns
    from slwarp.scans.patterns import named_set

    pats = torch.as_tensor(named_set("random6", PROJECTOR.width, PROJECTOR.height).patterns)
    m = evaluate_patterns(model, pats, batch, DesignOptions(count=6))  # backend "auto": the twin on the CPU
    assert 0.0 < m["loss"] < 1.0 and 0.0 <= m["miss_rate"] <= 1.0


def test_a_short_design_lowers_its_objective():
    # 3 patterns: with every pixel's code spanning 0..1, 2 patterns leave a pixel one bit (which frame is brighter)
    # and nothing for the descent to shape
    opts = DesignOptions(count=3, iterations=30, pixels=512, validation_pixels=1024, report_every=10, seed=3)
    res = design_patterns(CAMERA, PROJECTOR, DEPTH_RANGE_MM, opts, baselines=())
    h = res.history
    assert h["iteration"] == [0, 10, 20, 30]
    assert min(h["loss"][1:]) < h["loss"][0] - 0.01
    assert res.patterns.names == ["design3_0", "design3_1", "design3_2"]
    p = res.patterns.patterns
    assert p.shape == (3, PROJECTOR.height, PROJECTOR.width)
    # 8-bit values, each pixel's code spanning 0..1
    assert np.allclose(p * 255, np.rint(p * 255), atol=1e-4)
    assert np.allclose(p.max(0), 1.0) and np.allclose(p.min(0), 0.0)


def test_a_short_windowed_design_lowers_its_objective():
    # the camera's blur as modelled: this checks the windowed objective's descent, and on the small rig the spread's
    # draws of the blur make 20 steps too noisy to compare (full-size rigs: docs/accuracy.md, section 40)
    opts = DesignOptions(count=3, iterations=20, pixels=2048, validation_pixels=4096, report_every=10, seed=3, window=1,
                         noise=NoiseModel(blur_spread=1.0))
    res = design_patterns(CAMERA, PROJECTOR, DEPTH_RANGE_MM, opts, baselines=("random6",))
    h = res.history
    assert min(h["loss"][1:]) < h["loss"][0]
    assert res.options.window == 1 and 0.0 <= res.baselines["random6"]["miss_rate"] <= 1.0
    with pytest.raises(ValueError, match="window"):
        DesignOptions(window=-1)
    with pytest.raises(ValueError, match="window-step"):
        DesignOptions(window=1, window_step=0)
    with pytest.raises(ValueError, match="give the window too"):
        DesignOptions(window=0, window_step=3)


def test_the_design_command_scores_spaced_windows_by_default_only_where_they_were_best():
    """3 patterns or fewer on a 1280 px camera: 5 x 5 windows 3 px apart; 4 patterns, or a small camera: each pixel."""
    from slwarp.cli.design import default_window

    assert default_window(3, 1280) == default_window(2, 1920) == (2, 3)
    assert default_window(4, 1280) == default_window(3, 320) == (0, 1)


def test_a_binary_design_sharpens_during_the_descent():
    """binary=True: the patterns come out black and white, every pixel keeping a code, and the descent that
    sharpens them scores better on the validation batch than rounding the grey design of the same steps."""
    from slwarp.design import evaluate_patterns
    from slwarp.design.objective import CodeModel as Model

    common = dict(count=4, iterations=60, pixels=512, validation_pixels=1024, report_every=20, seed=3)
    grey = design_patterns(CAMERA, PROJECTOR, DEPTH_RANGE_MM, DesignOptions(**common), baselines=())
    sharp = design_patterns(CAMERA, PROJECTOR, DEPTH_RANGE_MM, DesignOptions(**common, binary=True), baselines=())
    b = sharp.patterns.patterns
    assert set(np.unique(b)) <= {0.0, 1.0} and (b.max(0) == 1).all() and (b.min(0) == 0).all()
    opts = DesignOptions(**common)
    model = Model(CAMERA, PROJECTOR, DEPTH_RANGE_MM, opts.noise, step_px=opts.step_px)
    g = torch.Generator()
    g.manual_seed(opts.seed + 7919)  # the designs' own validation batch
    val = model.batch(opts.validation_pixels, 4, g)
    rounded = evaluate_patterns(model, torch.as_tensor(binarise(grey.patterns.patterns)), val, opts)
    assert sharp.final["loss"] < rounded["loss"] - 0.01, (sharp.final, rounded)


def test_design_patterns_command_writes_a_set_that_simulate_projects(tmp_path, capsys):
    out = tmp_path / "design"
    assert cli_main(["design-patterns", "--rig", "small", "--count", "3", "--iterations", "4", "--pixels", "256",
                     "--device", "cpu", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "designed 3" in text and "random6" in text and "gray7" in text and "each pixel alone" in text
    for f in ("patterns.yaml", "design.json", "design.png", "design3_0.png", "design3_2.png"):
        assert (out / f).is_file(), f
    doc = json.loads((out / "design.json").read_text())
    assert doc["history"]["iteration"][-1] == 4 and doc["options"]["count"] == 3
    pset = read_pattern_set(out)
    assert pset.names == ["design3_0", "design3_1", "design3_2"]
    scan_dir = tmp_path / "scan"
    assert cli_main(["simulate", "--scene", "bunny", "--rig", "small", "--patterns", f"random6+{out}",
                     "--out", str(scan_dir), "--device", "cpu"]) == 0
    assert cli_main(["info", str(scan_dir), "--roles", "--frames", "designed"]) == 0
    assert "designed" in capsys.readouterr().out


def test_a_set_designed_for_spaced_windows_tells_the_search_its_step(tmp_path, capsys):
    """design-patterns --window-step 3 writes window_step into the set's roles; simulate carries them into scan.yaml,
    and the reconstruction's depth search takes that step unless search_window_step is set."""
    from slwarp.neural.config import preset
    from slwarp.neural.start import window_step_of
    from slwarp.scans.scan import load_scan

    out = tmp_path / "design"
    assert cli_main(["design-patterns", "--rig", "small", "--count", "3", "--window", "1", "--window-step", "3",
                     "--iterations", "2", "--pixels", "256", "--device", "cpu", "--out", str(out)]) == 0
    assert "window_step=3" in capsys.readouterr().out
    pset = read_pattern_set(out)
    assert [r.window_step for r in pset.frame_roles()] == [3, 3, 3]
    scan_dir = tmp_path / "scan"
    assert cli_main(["simulate", "--scene", "spheres", "--rig", "small", "--patterns", f"random6+{out}",
                     "--out", str(scan_dir), "--device", "cpu"]) == 0
    scan = load_scan(scan_dir)
    designed = scan.select("designed")
    auto = preset("cpu-hashgrid")
    assert auto.init.search_window_step == 0  # auto is every preset's default
    assert window_step_of(designed, auto, 3) == 3 and window_step_of(scan, auto, 6) == 1  # random 6 first
    assert window_step_of(designed, preset("cpu-hashgrid", search_window_step=2), 3) == 2


@pytest.mark.parametrize("argv, message", [
    (["--rig", "small", "--scan", "x"], "either --rig"),
    (["--rig", "nowhere"], "unknown rig"),
    (["--rig", "small", "--count", "1"], "at least 2 patterns"),
    (["--rig", "small", "--depth-range", "900,500"], "--depth-range"),
    (["--rig", "small", "--modulation", "0.5"], "--modulation"),
    (["--rig", "small", "--modulation", "0.9,0.1"], "modulation range"),
    (["--rig", "small", "--blur-px", "-1"], "blur"),
    (["--rig", "small", "--blur-spread", "0.5"], "spread"),
    (["--rig", "small", "--count", "4", "--window-step", "3"], "give the window too"),
])
def test_design_patterns_bad_input_is_one_line(tmp_path, capsys, argv, message):
    assert cli_main(["design-patterns", "--out", str(tmp_path / "o"), "--device", "cpu", *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1
