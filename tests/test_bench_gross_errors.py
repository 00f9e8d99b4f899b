"""bench.gross_errors: where a preset's gross errors come from (the stage, the depth edge, GC(7) there)."""
import json

import numpy as np

from bench.gross_errors import edge_distance, first_wrong, main, markdown


def test_edge_distance_counts_rings_to_a_farther_or_nearer_surface():
    gt = np.full((9, 9), 800.0)
    gt[3:6, 3:6] = 500.0  # a square 300 mm in front
    ref = np.ones(gt.shape, bool)
    farther = edge_distance(gt, ref, +1)
    nearer = edge_distance(gt, ref, -1)
    assert farther[3, 3] == 1 and farther[4, 4] == 2  # the square's outline, its centre two rings in
    assert (farther[gt > 600] == 99).all()  # nothing lies behind the wall
    assert nearer[2, 2] == 1 and nearer[1, 4] == 2 and nearer[0, 0] == 3 and nearer[4, 4] == 99
    ref[3:6, 3:6] = False  # without ground truth the square is no surface
    assert (edge_distance(gt, ref, -1) == 99).all()


def test_first_wrong_names_the_stage_that_brought_each_wrong_depth():
    gt = np.full((1, 4), 500.0)
    maps = {"depth": np.array([[800.0, 500.0, np.nan, 800.0]]),  # pixels 0 and 3 wrong from the start
            "repair": np.array([[800.0, 800.0, np.nan, 500.0]]),  # pixel 1 made wrong, 3 made right
            "fill": np.array([[800.0, 800.0, 800.0, 800.0]])}  # pixel 2 filled wrong, 3 wrong again
    gross = np.array([[True, True, True, True]])
    assert first_wrong(maps, gt, gross, 20.0) == {"depth": 2, "repair": 1, "fill": 1}


def test_a_tiny_run_traces_its_gross_pixels(tmp_path, capsys):
    """The tiny preset on the small rig's spheres (CPU): every gross pixel is traced to a stage, and the stage-by-stage
    extraction ends with the map the run itself made (its RMSE)."""
    out = tmp_path / "g.json"
    assert main(["--preset", "tiny", "--set", "iters=60,init_iters=30", "--rigs", "small", "--scenes", "spheres",
                 "--device", "cpu", "--json", str(out)]) == 0
    [row] = json.loads(out.read_text())["rows"]
    assert row["gross"] == row["behind"] + row["in_front"] == sum(row["first_wrong_after"].values()) > 0
    assert row["gross"] == sum(row["fates"].values())
    assert row["rmse_without_gross"] < row["rmse"]
    assert abs(row["rmse"] - row["run_rmse"]) < 1e-6 * row["rmse"]
    assert "| small | spheres |" in capsys.readouterr().out
    assert markdown([row]).count("\n") == 2


def test_a_designed_set_needs_its_folder():
    import pytest

    with pytest.raises(SystemExit, match="needs --designs"):
        main(["--frames", "design3", "--rigs", "small", "--scenes", "spheres", "--device", "cpu"])
