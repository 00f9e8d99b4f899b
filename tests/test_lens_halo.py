"""The lens halo fitted to a scan (pattern_model.fit_halo) and the trainer's `pattern_halo: auto`: a halo where
the camera saw one, none where it saw none, the share kept in the checkpoint and taken back on resume."""
import numpy as np
import pytest

from slwarp.neural.pattern_model import fit_halo, with_halo


@pytest.fixture(scope="module")
def halo_scans():
    """{camera model: the small rig's steps scene, 7 Gray code column images (no inverses)}, linear and halo."""
    from slwarp.sim.simulate import camera_model, simulate_scene

    return {cam: simulate_scene("steps", "gray7", rig="small", options=camera_model(cam, seed=0), device="cpu")
            for cam in ("linear", "halo")}


@pytest.mark.parametrize("camera, lo, hi", [("linear", 0.0, 0.0), ("halo", 0.05, 0.15)])
def test_fit_halo_finds_the_cameras_halo_at_the_true_depth(halo_scans, camera, lo, hi):
    """At the true depth the fit gives the halo the simulator's camera has (0.1 over 40 px) within a grid step,
    and exactly none for a camera without one; the misfit is reported per share tried."""
    scan = halo_scans[camera]
    gt = np.where(scan.mask, scan.gt_depth, np.nan).astype(np.float32)
    share, fit = fit_halo(gt, scan.camera, scan.projector, scan.images, scan.patterns)
    assert lo <= share <= hi and fit["share"] == share
    assert len(fit["misfits"]) == len(fit["shares"]) and fit["shares"][0] == 0.0
    best = int(np.argmin(fit["misfits"]))
    assert (best == 0) == (camera == "linear")


def test_fit_halo_without_depth_gives_none(halo_scans):
    scan = halo_scans["halo"]
    share, fit = fit_halo(np.full(scan.gt_depth.shape, np.nan, np.float32), scan.camera, scan.projector,
                          scan.images, scan.patterns)
    assert share == 0.0 and all(np.isnan(fit["misfits"]))


def test_trainer_fits_the_halo_and_a_resumed_run_keeps_it(halo_scans, tmp_path):
    """pattern_halo auto: the trainer fits the share after the depth search and trains on the patterns through
    that lens; the checkpoint holds the share and a resumed run takes it without fitting again."""
    from slwarp.neural.config import preset
    from slwarp.neural.training import Trainer

    scan = halo_scans["halo"]
    cfg = preset("tiny", device="cpu", iters=4, init_iters=2, pattern_halo="auto", checkpoint_every=1000)
    trainer = Trainer(scan, cfg, out_dir=tmp_path, progress=False)
    assert 0.05 <= trainer.halo_share <= 0.2 and trainer.halo_fit["share"] == trainer.halo_share
    np.testing.assert_allclose(trainer.scan.patterns, with_halo(scan.patterns, trainer.halo_share, 40.0), atol=1e-6)
    assert "halo fit" in trainer.setup_phases
    trainer.train()
    trainer.save_checkpoint()
    resumed = Trainer(scan, cfg.with_options(iters=6), out_dir=tmp_path, resume=True, progress=False)
    assert resumed.halo_share == pytest.approx(trainer.halo_share) and resumed.halo_fit is None
    np.testing.assert_allclose(resumed.scan.patterns, trainer.scan.patterns, atol=1e-6)
    # a given share is used as it is, from the start
    fixed = Trainer(scan, cfg.with_options(pattern_halo=0.2), progress=False)
    assert fixed.halo_share == 0.2 and fixed.halo_fit is None and "halo fit" not in fixed.setup_phases


def test_the_fits_device_blur_is_the_lens_halo():
    """fit_halo blurs the halo on a GPU with blur_patterns: the same as with_halo's OpenCV blur (edges replicated)."""
    import torch

    from slwarp.neural.pattern_model import blur_patterns

    rng = np.random.default_rng(0)
    pats = (rng.random((2, 60, 90)) > 0.5).astype(np.float32)
    np.testing.assert_allclose(blur_patterns(torch.as_tensor(pats), 8.0).numpy(), with_halo(pats, 1.0, 8.0), atol=1e-5)


def test_a_lens_with_a_halo_trains_with_the_lens_schedule(halo_scans, tmp_path):
    """lens_variance_lr_factor / lens_lambda_reg replace variance_lr_factor / lambda_reg only where the scan's lens
    has a halo (fitted or given): Adam's variance group and the Eikonal weight change, the run's identity and its
    checkpoint's config stay those asked for, a resumed run trains the same way, and a lens without one keeps both."""
    from slwarp.neural.config import preset
    from slwarp.neural.training import Trainer

    lens = dict(lens_variance_lr_factor=16.0, lens_lambda_reg=0.5)
    cfg = preset("tiny", device="cpu", iters=2, init_iters=2, pattern_halo="auto", checkpoint_every=1000, **lens)

    def variance_lr(trainer):
        params = {id(p) for p in trainer.renderer.variance.parameters()}
        return next(g["base_lr"] for g in trainer.optimizer.param_groups if params & {id(p) for p in g["params"]})

    halo = Trainer(halo_scans["halo"], cfg, out_dir=tmp_path, progress=False)
    assert halo.halo_share > 0 and halo.lens_schedule == {"variance_lr_factor": 16.0, "lambda_reg": 0.5}
    assert halo.cfg.schedule.lambda_reg == 0.5 and variance_lr(halo) == pytest.approx(16.0 * cfg.schedule.lr)
    assert halo.declared_cfg is cfg and halo.cfg != cfg  # validate() returns the config itself
    assert halo.state()["config"]["schedule"]["variance_lr_factor"] == cfg.schedule.variance_lr_factor
    halo.train()
    halo.save_checkpoint()
    resumed = Trainer(halo_scans["halo"], cfg.with_options(iters=3), out_dir=tmp_path, resume=True, progress=False)
    assert resumed.lens_schedule == halo.lens_schedule and variance_lr(resumed) == variance_lr(halo)

    linear = Trainer(halo_scans["linear"], cfg, progress=False)
    assert linear.halo_share == 0 and linear.lens_schedule is None and linear.cfg is linear.declared_cfg
    assert variance_lr(linear) == pytest.approx(cfg.schedule.variance_lr_factor * cfg.schedule.lr)
    # a given halo counts as one; without the lens options a halo changes nothing
    assert Trainer(halo_scans["linear"], cfg.with_options(pattern_halo=0.1), progress=False).lens_schedule is not None
    plain = preset("tiny", device="cpu", iters=2, init_iters=2, pattern_halo=0.1)
    assert Trainer(halo_scans["linear"], plain, progress=False).lens_schedule is None


def test_the_command_says_how_the_lens_trained_and_config_yaml_records_it(halo_scans, tmp_path, capsys):
    """`slwarp reconstruct` prints the fitted halo and the lens schedule it trained with; config.yaml keeps both
    under `fitted` and the declared options in its sections."""
    import re

    import yaml

    from slwarp.cli import main as cli_main

    folder = tmp_path / "scan"
    halo_scans["halo"].save(folder)
    out = tmp_path / "out"
    assert cli_main(["reconstruct", str(folder), "--out", str(out), "--device", "cpu", "--preset", "tiny",
                     "--iters", "2", "--init-iters", "2", "--mc-resolution", "32", "--pattern-halo", "auto",
                     "--lens-variance-lr-factor", "16", "--lens-lambda-reg", "0.5"]) == 0
    printed = capsys.readouterr().out
    share = re.search(r"lens halo: (\d\.\d+) of the light", printed)
    assert share and 0.05 <= float(share.group(1)) <= 0.15
    assert "trained for a lens with a halo: variance_lr_factor 16, lambda_reg 0.5" in printed
    doc = yaml.safe_load((out / "config.yaml").read_text())
    assert doc["fitted"]["lens_schedule"] == {"variance_lr_factor": 16.0, "lambda_reg": 0.5}
    assert doc["schedule"]["lambda_reg"] == 0.1 and doc["schedule"]["lens_lambda_reg"] == 0.5
