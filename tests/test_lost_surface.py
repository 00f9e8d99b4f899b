"""A field that lost the surface (most lit pixels without a depth inside the depth range while the depth search had
found one) is said: timings.json's "surface_lost", a warning from `slwarp reconstruct`, a failed row in a batch."""
import json

import numpy as np
import pytest

from slwarp.neural.reconstruct import LOST_SURFACE_SHARE, lost_surface, lost_surface_message, surface_shares


def _counts(measured=0, no_contrast=0, no_surface=0, out_of_range=0, low_confidence=0):
    return {"measured": measured, "no_contrast": no_contrast, "no_surface": no_surface,
            "out_of_range": out_of_range, "low_confidence": low_confidence}


def test_the_rule_reads_the_lit_pixels_fates_and_the_search():
    searched = np.r_[np.full(950, 800.0), np.full(1050, np.nan)]  # 950 of the 1000 lit pixels
    # the oblique boxes run of 2026-11-27: 92% of the lit pixels out of range
    lost = lost_surface(_counts(measured=60, no_contrast=1000, out_of_range=920, low_confidence=20), searched)
    assert lost == pytest.approx({"lost": 0.92, "searched": 0.95})
    # a healthy run loses a few percent
    assert lost_surface(_counts(measured=960, no_contrast=1000, no_surface=10, out_of_range=5, low_confidence=25),
                        searched) is None
    # where the search found nothing either, the field is not to blame (the range or the scan is)
    assert lost_surface(_counts(measured=10, no_contrast=1000, out_of_range=990), np.full(2000, np.nan)) is None
    # without a search the fates decide; no lit pixel: nothing to say
    assert lost_surface(_counts(measured=10, no_contrast=1000, no_surface=990), None)["searched"] is None
    assert lost_surface(_counts(no_contrast=50), None) is None
    edge = int(1000 * LOST_SURFACE_SHARE)
    assert lost_surface(_counts(measured=1000 - edge, out_of_range=edge), None) is None
    # the shares it reads, said for every run (timings.json's surface_shares)
    assert surface_shares(_counts(measured=960, no_contrast=1000, no_surface=10, out_of_range=5, low_confidence=25),
                          searched) == pytest.approx({"lost": 0.015, "searched": 0.95})
    assert surface_shares(_counts(no_contrast=50), None) is None
    msg = lost_surface_message(lost, (500.0, 1500.0))
    assert "92% of the lit pixels" in msg and "500-1500 mm" in msg and "95%" in msg and "--seed" in msg


@pytest.fixture(scope="module")
def small_scan():
    """The small rig's steps scene with the paper's 6 random patterns."""
    from slwarp.sim.simulate import SimOptions, simulate_scene

    return simulate_scene("steps", "random6", rig="small", options=SimOptions(seed=0), device="cpu")


def _collapse_extractions(monkeypatch, times: int | None) -> list:
    """The extraction leaves every lit pixel out of range (as a field that lost the surface does) on its first
    `times` calls (None: always); returns the seeds of the runs extracted, in order."""
    import slwarp.neural.reconstruct as rec
    from slwarp.neural.extraction.state import FATE

    real = rec.extract_depth
    seeds = []

    def collapsing(trainer, valid, **kw):
        seeds.append(trainer.cfg.runtime.seed)
        depth, confidence, mesh, timings, fate = real(trainer, valid, **kw)
        if times is not None and len(seeds) > times:
            return depth, confidence, mesh, timings, fate
        fate = np.where(np.asarray(valid, bool), FATE["out_of_range"], fate).astype(fate.dtype)
        return np.full_like(depth, np.nan), np.full_like(confidence, np.nan), mesh, timings, fate

    monkeypatch.setattr(rec, "extract_depth", collapsing)
    return seeds


@pytest.fixture
def lose_the_surface(monkeypatch):
    """Every training loses the surface."""
    return _collapse_extractions(monkeypatch, None)


TINY = ["--device", "cpu", "--preset", "tiny", "--iters", "2", "--init-iters", "2", "--mc-resolution", "32"]


def test_the_command_warns_and_timings_json_records_it(small_scan, tmp_path, capsys, lose_the_surface):
    from slwarp.cli import main as cli_main

    folder = tmp_path / "scan"
    small_scan.save(folder)
    assert cli_main(["reconstruct", str(folder), "--out", str(tmp_path / "out"), *TINY]) == 0
    printed = capsys.readouterr()
    assert "the training with seed 0 lost the surface (100% of the lit pixels" in printed.out
    assert "trained again with seed 1, which lost it too" in printed.out
    assert "warning: the field lost the surface: 100% of the lit pixels got no depth inside the depth range" in printed.err
    timings = json.loads((tmp_path / "out" / "timings.json").read_text())
    lost = timings["surface_lost"]
    assert lost["lost"] == 1.0 and lost["searched"] > LOST_SURFACE_SHARE
    assert timings["lost_surface_retry"]["seed"] == 0 and lose_the_surface == [0, 1]


def test_a_second_training_with_the_next_seed_replaces_a_lost_one(small_scan, tmp_path, capsys, monkeypatch):
    import yaml

    from slwarp.cli import main as cli_main

    seeds = _collapse_extractions(monkeypatch, 1)
    folder = tmp_path / "scan"
    small_scan.save(folder)
    assert cli_main(["reconstruct", str(folder), "--out", str(tmp_path / "out"), *TINY]) == 0
    printed = capsys.readouterr()
    assert "trained again with seed 1, which kept it" in printed.out and "warning" not in printed.err
    assert seeds == [0, 1]
    timings = json.loads((tmp_path / "out" / "timings.json").read_text())
    assert timings["surface_lost"] is None and timings["lost_surface_retry"]["lost"] == 1.0
    # what the rule read on the kept run, and that it ran without a CUDA graph (the CPU has none)
    shares = timings["surface_shares"]
    assert shares["lost"] < LOST_SURFACE_SHARE < shares["searched"] and timings["graph_captured"] is False
    assert np.isfinite(np.load(tmp_path / "out" / "depth.npy")).any()
    assert yaml.safe_load((tmp_path / "out" / "config.yaml").read_text())["runtime"]["seed"] == 1  # what trained


def test_no_second_training_when_asked_for_none(small_scan, tmp_path, capsys, lose_the_surface):
    from slwarp.cli import main as cli_main

    folder = tmp_path / "scan"
    small_scan.save(folder)
    assert cli_main(["reconstruct", str(folder), "--out", str(tmp_path / "out"), *TINY,
                     "--no-retry-lost-surface"]) == 0
    assert "warning: the field lost the surface" in capsys.readouterr().err and lose_the_surface == [0]


def test_a_batch_counts_the_scan_as_failed_and_keeps_its_files(small_scan, tmp_path, lose_the_surface):
    from slwarp.batch import BatchOptions, ScanJob, run_scans
    from slwarp.neural.config import preset

    small_scan.save(tmp_path / "scan")
    cfg = preset("tiny", iters=2, init_iters=2, mc_resolution=32).with_options(device="cpu")
    rows = run_scans([ScanJob("scan", str(tmp_path / "scan"), str(tmp_path / "out"))], cfg, BatchOptions(log=False))
    assert rows[0].status == "failed" and rows[0].error.startswith("the field lost the surface")
    assert (tmp_path / "out" / "depth.npy").is_file()
