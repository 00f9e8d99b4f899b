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


def test_a_scene_outside_the_depth_range_is_said_apart_from_a_lost_field():
    """Few lit pixels with depth while the search found little: the range is to blame, not the training."""
    from slwarp.neural.reconstruct import range_missed, range_missed_message

    few = np.r_[np.full(40, 800.0), np.full(1960, np.nan)]  # the search: 40 of the 1000 lit pixels

    def missed_in(counts, search):
        return range_missed(counts, surface_shares(counts, search), counts["measured"])

    # a field trained outside the scene: its surfaces fail the confidence check, or lie out of range
    counts = _counts(measured=30, no_contrast=1000, out_of_range=300, low_confidence=670)
    missed = missed_in(counts, few)
    assert missed == pytest.approx({"searched": 0.04, "with_depth": 0.03})
    assert lost_surface(counts, few) is None  # not the field's failure
    msg = range_missed_message(missed, (3000.0, 4000.0))
    assert "3000-4000 mm on only 4%" in msg and "3% of them have one" in msg and "--depth-range" in msg
    # a healthy run, a lost field (the search found the surface), a run without a search and a narrow range that
    # keeps its part of the scene are not range misses
    assert missed_in(_counts(measured=960, no_contrast=1000, no_surface=40), np.full(1000, 800.0)) is None
    assert missed_in(_counts(measured=30, no_contrast=1000, out_of_range=970), np.full(1000, 800.0)) is None
    assert missed_in(counts, None) is None
    assert missed_in(_counts(measured=600, no_contrast=1000, out_of_range=400), few) is None


def test_the_command_warns_when_the_scene_lies_outside_the_depth_range(small_scan, tmp_path, capsys):
    from slwarp.cli import main as cli_main

    folder = tmp_path / "scan"
    small_scan.save(folder)
    out = tmp_path / "out"
    assert cli_main(["reconstruct", str(folder), "--out", str(out), *TINY, "--depth-range", "3000,4000"]) == 0
    printed = capsys.readouterr()
    assert "warning: the depth search found a depth inside the depth range 3000-4000 mm on only" in printed.err
    assert "lost the surface" not in printed.out + printed.err  # no second training: the field is not to blame
    timings = json.loads((out / "timings.json").read_text())
    assert timings["range_missed"]["searched"] < 0.25 and timings["range_missed"]["with_depth"] < 0.5
    assert timings["surface_lost"] is None
