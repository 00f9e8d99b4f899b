"""bench/stage_drops.py without a run: each stage's drops scored against a reference, and the exchange with GC(7)."""
import numpy as np
import pytest

from bench import stage_drops


def test_each_stage_is_scored_by_the_depths_it_dropped():
    ref = np.full((2, 4), 1000.0, np.float32)
    ref[1, 3] = np.nan  # the reference lacks one pixel
    depth = np.array([[1000.5, 1010.0, 1001.0, 1020.0], [999.0, 1003.0, 1000.0, 1000.0]], np.float32)
    a = depth.copy()
    a[0, 1] = a[0, 3] = np.nan  # the first stage drops two wrong depths
    b = a.copy()
    b[0, 0] = b[1, 0] = b[1, 3] = np.nan  # the second two right ones and one the reference lacks
    gc7 = np.full_like(ref, 1000.0)
    gc7[0, 0] = 1050.0
    rows = stage_drops.drop_rows({"depth": depth, "first": a, "unchanged": a.copy(), "second": b}, ref, gc7, 2.0)
    assert [r["stage"] for r in rows] == ["first", "second"]  # a stage that dropped nothing has no row
    assert rows[0] == {"stage": "first", "dropped": 2, "with_reference": 2, "right_share": 0.0, "other_right": 1.0}
    assert rows[1]["dropped"] == 3 and rows[1]["with_reference"] == 2 and rows[1]["right_share"] == 1.0
    assert rows[1]["other_right"] == 0.5
    ex = stage_drops.exchange(b, gc7, ref, 2.0)
    assert ex["only_other"] == 5 and ex["only_other_right_share"] == 0.75  # gc7 right on 3 of the 4 scored
    assert ex["only_final"] == 0 and ex["only_final_right_share"] is None
    md = stage_drops.markdown(rows, ex, 2.0)
    assert "| first | 2 | 2 | 0% | 100% |" in md and "GC(7) has and the map lacks 5 pixels (75%" in md


def test_a_folder_without_a_finished_run_is_refused(tmp_path):
    with pytest.raises(SystemExit, match="not a finished run"):
        stage_drops.main([str(tmp_path), "--scan", str(tmp_path)])
