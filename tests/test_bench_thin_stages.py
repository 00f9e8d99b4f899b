"""bench/thin_stages.py's bookkeeping without training: the ok / wrong / none shares per part and the table."""
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import thin_stages  # noqa: E402


def test_shares_split_ok_wrong_and_missing_pixels():
    gt = np.full((2, 4), 600.0)
    depth = np.array([[600.5, 603.0, 900.0, np.nan], [601.0, np.nan, 610.0, 599.0]])
    part = np.array([[True, True, True, True], [False, False, False, False]])
    s = thin_stages.shares(depth, gt, part)
    assert s == {"ok": 0.5, "wrong": 0.25, "none": 0.25, "mae_ok": 1.75}
    rest = thin_stages.shares(depth, gt, ~part)
    assert rest["ok"] == 0.5 and rest["wrong"] == 0.25 and rest["none"] == 0.25 and rest["mae_ok"] == 1.0
    assert thin_stages.shares(np.full((2, 4), np.nan), gt, part)["mae_ok"] is None


def test_render_tabulates_the_stages_it_has():
    stage = {"rods": {"ok": 0.0, "wrong": 1.0, "none": 0.0, "mae_ok": None},
             "rest": {"ok": 0.9, "wrong": 0.05, "none": 0.05, "mae_ok": 0.2}}
    doc = {"date": "2026-11-23", "scene": "rods", "rig": "small", "preset": "tiny", "overrides": {"iters": 10},
           "device": "cpu", "thin_px": 7, "wall_s": 1.0, "stages": {"trained mesh": stage, "extracted": stage},
           "sdf": {"trained": {"median": 120.0, "near": 0.0}},
           "extracted": {"mae": 1.5, "completeness": 0.9, "dropped": {}, "repair": None}}
    md = thin_stages.render(doc)
    assert "--set iters=10" in md
    assert "| trained mesh | 0.0% | 100.0% | 0.0% | 90.0% | 5.0% | 5.0% | - | 0.200 |" in md
    assert "search |" not in md and "trained: median 120.0, within 1.5 mm 0.0%" in md
