"""`slwarp decode` on a simulated scan on disk: every method, its outputs, frame selection, missing frames."""
import json

import cv2
import numpy as np
import pytest

from slwarp.cli import main as cli_main
from slwarp.scans.scan import load_scan, read_depth
from slwarp.sim.simulate import SimOptions, simulate_scene


@pytest.fixture(scope="module")
def scan_dir(tmp_path_factory):
    folder = tmp_path_factory.mktemp("scan")
    scan = simulate_scene("boxes", "gt+cgc6+cgc7+hpmp6+npmp6+ps4", "small", SimOptions(seed=1), device="cpu")
    scan.save(folder)
    return folder


# (method, --frames, MAE bound in mm on the small rig, whose projector has half the default resolution,
# completeness bound: N-PMP leaves pixels whose two phases disagree by more than 1 px invalid)
CASES = [
    ("gt", None, 2.0, 0.95),
    ("gc", "gc_col_b[0-6],gc_col_b[0-6]_inv", 12.0, 0.95),
    ("gc-interp", "gc_col_b[0-6]", 2.0, 0.95),
    ("gc-interp", "gc_col_b[0-5]", 2.5, 0.95),
    ("cgc", "gc_col_b[0-2],ps_col_p160_*", 8.0, 0.95),
    ("cgc", "gc_col_b[0-3],ps_col_p80_*", 4.0, 0.95),
    ("hpmp", None, 4.0, 0.95),
    ("npmp", None, 2.5, 0.8),
    ("ps", None, 30.0, 0.9),
]


@pytest.mark.parametrize("method,frames,mae,complete", CASES)
def test_cli_decode_every_method(scan_dir, tmp_path, capsys, method, frames, mae, complete):
    out = tmp_path / "out"
    argv = ["decode", str(scan_dir), "--method", method, "--out", str(out)] + (["--frames", frames] if frames else [])
    assert cli_main(argv) == 0
    printed = capsys.readouterr().out
    assert f"with {method}" in printed and "MAE mm" in printed
    for f in ("depth.npy", "depth.png", "depth_color.png", "points.ply", "metrics.json", "error_map.png", "projector_col.npy"):
        assert (out / f).is_file(), f
    depth = np.load(out / "depth.npy")
    png = cv2.imread(str(out / "depth.png"), cv2.IMREAD_UNCHANGED)
    assert png.dtype == np.uint16 and png.shape == depth.shape
    fin = np.isfinite(depth)
    assert np.array_equal(png > 0, fin) and np.abs(png[fin] / 10.0 - depth[fin]).max() <= 0.05 + 1e-3
    assert np.abs(read_depth(out / "depth.png") - depth)[fin].max() <= 0.05 + 1e-3
    doc = json.loads((out / "metrics.json").read_text())
    assert doc["method"] == method and doc["triangulation"] == "col"
    m = doc["metrics"]
    assert m["completeness"] > complete and m["mae"] < mae
    if frames:
        scan = load_scan(scan_dir)
        assert set(doc["frames"]) <= set(scan.select(frames).names)


def test_cli_decode_gc6_frames(scan_dir, tmp_path):
    assert cli_main(["decode", str(scan_dir), "--method", "gc-interp", "--frames", "gc_col_b[0-5]",
                     "--out", str(tmp_path / "o")]) == 0
    doc = json.loads((tmp_path / "o" / "metrics.json").read_text())
    assert doc["frames"] == [f"gc_col_b{k}" for k in range(6)]


def test_cli_decode_missing_frames_and_bad_input(scan_dir, tmp_path, capsys):
    assert cli_main(["decode", str(scan_dir), "--method", "npmp", "--frames", "gc_col_b*", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert "method npmp needs two 3-step phase shifts" in err and "phase:col:period=48" in err
    assert err.strip().endswith("the scan has: gray:col:bit=0-6 (+inv)")
    assert len(err.strip().splitlines()) == 1
    assert cli_main(["decode", str(scan_dir), "--method", "gc", "--frames", "nope*", "--out", str(tmp_path / "x")]) == 2
    assert "no frame matches 'nope*'" in capsys.readouterr().err
    assert cli_main(["decode", str(tmp_path / "missing"), "--method", "gc", "--out", str(tmp_path / "x")]) == 2
    assert "scan not found" in capsys.readouterr().err
    assert cli_main(["decode", str(scan_dir), "--method", "gc", "--triangulation", "midpoint", "--out", str(tmp_path / "x")]) == 2
    assert "midpoint triangulation needs both" in capsys.readouterr().err


def test_cli_decode_on_vertical_rig_by_role(tmp_path, capsys):
    """On the vertical rig the row codes carry depth: decoding them triangulates with the row plane; decoding
    the column codes alone works but warns that they see almost none of the baseline."""
    folder = tmp_path / "v"
    simulate_scene("torus", "gray7+gray7_row", "small-vertical", SimOptions(seed=2), device="cpu").save(folder)
    assert cli_main(["decode", str(folder), "--method", "gc-interp", "--frames", "gray:row", "--out", str(tmp_path / "r")]) == 0
    out = capsys.readouterr().out
    assert "triangulation: row" in out and "warning" not in out
    doc = json.loads((tmp_path / "r" / "metrics.json").read_text())
    assert doc["triangulation"] == "row" and doc["frames"] == [f"gc_row_b{k}" for k in range(7)]
    assert doc["metrics"]["mae"] < 1.0
    assert cli_main(["decode", str(folder), "--method", "gc-interp", "--frames", "gray:col", "--out", str(tmp_path / "c")]) == 0
    out = capsys.readouterr().out
    assert "triangulation: col" in out and "warning: the decoded projector cols see only 0% of the baseline" in out
