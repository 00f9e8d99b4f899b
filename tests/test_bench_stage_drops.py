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


def test_a_runs_extraction_replayed_on_its_own_frames_drops_what_the_run_dropped(tmp_path):
    import json

    from slwarp.neural.config import preset
    from slwarp.neural.reconstruct import reconstruct
    from slwarp.scans.scan import load_scan
    from slwarp.sim.simulate import SimOptions, simulate_scene

    folder = tmp_path / "scan"
    simulate_scene("spheres", "random6+gray7", rig="small", options=SimOptions(seed=3)).save(folder)
    scan = load_scan(folder)
    cfg = preset("tiny", device="cpu", iters=20, init="sphere", init_iters=10, rays=64, mc_resolution=32)
    res = reconstruct(scan.select("rand*"), cfg, out_dir=tmp_path / "run", progress=False)
    res.wait_written()
    out = tmp_path / "drops.json"
    # the scan holds 13 frames, the run trained on 6: the replay takes the run's frames from its checkpoint
    assert stage_drops.main([str(tmp_path / "run"), "--scan", str(folder), "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    # each stage's drops as the run counted them (by the fate it gives them; the first stage's, against the lit
    # pixels, are no row), and the replay's final map the run's
    from slwarp.neural.extraction.runner import build_stages

    fates = {st.name: st.drops or st.name for st in build_stages(cfg.extraction)}
    run_dropped = json.loads((tmp_path / "run" / "timings.json").read_text())["dropped"]
    first = fates["depth"]
    assert {fates[r["stage"]]: r["dropped"] for r in doc["rows"]} == \
        {k: v for k, v in run_dropped.items() if v and k != first}
    final = int(np.isfinite(np.load(tmp_path / "run" / "depth.npy")).sum())
    assert doc["rows"] and list(doc["pixels_with_depth"].values())[-1] == final
    assert all(0.0 <= r["right_share"] <= 1.0 for r in doc["rows"] if r["with_reference"])


def test_neighbour_support_counts_the_drops_the_final_maps_neighbours_vouch_for():
    ref = np.full((5, 5), 1000.0, np.float32)
    depth = ref.copy()
    depth[2, 2] = 1000.5  # a right depth in the middle of a flat patch
    depth[0, 0] = 1030.0  # a wrong depth in a corner (3 neighbours only)
    depth[4, 2] = 1000.0  # a right depth on the edge (5 neighbours)
    after = depth.copy()
    after[2, 2] = after[0, 0] = after[4, 2] = np.nan  # the stage drops all three
    final = after.copy()
    rows = stage_drops.support_rows({"depth": depth, "stage": after, "last": final}, ref, 2.0, 5)
    assert rows == [{"stage": "stage", "lost": 3, "lost_right": 2, "supported": 2, "supported_right": 2,
                     "supported_mae": 0.25, "supported_max": 0.5}]
    # with 8 neighbours asked, only the middle one; a dropped depth far from its neighbours' median is never vouched
    assert stage_drops.support_rows({"depth": depth, "stage": after, "last": final}, ref, 2.0, 8)[0]["supported"] == 1
    far = depth.copy()
    far[2, 2] = 1010.0
    row = stage_drops.support_rows({"depth": far, "stage": after, "last": final}, ref, 2.0, 5)[0]
    assert row["supported"] == 1 and row["lost_right"] == 1  # (4, 2) only; (2, 2) is off its neighbours and wrong
    md = stage_drops.support_markdown(rows, 2.0, 5)
    assert "| stage | 3 | 2 | 2 | 2 | 0.25 / 0.5 |" in md
