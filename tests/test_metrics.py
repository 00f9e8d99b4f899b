"""Depth metrics against hand-computed values, the table, and `slwarp evaluate` (good and bad input)."""
import json
import math

import numpy as np
import pytest

from slwarp.cli import main as cli_main
from slwarp.evaluation.metrics import METRICS_SCHEMA, depth_metrics, error_map, format_table, metrics_document
from slwarp.evaluation.outputs import write_depth_png
from slwarp.scans.scan import Scan, load_scan
from slwarp.scans.scanner import Camera, Projector, look_at_rotation


def test_depth_metrics_hand_computed():
    gt = np.array([[500.0, 600.0, 700.0], [800.0, np.nan, 900.0]])
    pred = np.array([[500.5, 598.0, np.nan], [806.0, 123.0, 900.0]])
    m = depth_metrics(pred, gt)
    err = np.array([0.5, 2.0, 6.0, 0.0])  # compared: gt and pred finite
    assert m["n_gt"] == 5 and m["n_valid"] == 4 and m["completeness"] == pytest.approx(0.8)
    assert m["mae"] == pytest.approx(err.mean()) and m["rmse"] == pytest.approx(np.sqrt((err**2).mean()))
    assert m["median"] == pytest.approx(1.25)
    assert m["over_1mm"] == pytest.approx(0.5) and m["over_2mm"] == pytest.approx(0.25)  # 2.0 is not above 2
    assert m["over_5mm"] == pytest.approx(0.25)


def test_depth_metrics_mask_and_empty():
    gt = np.full((4, 4), 700.0)
    pred = gt + 3.0
    pred[0] = np.nan
    mask = np.zeros((4, 4), bool)
    mask[:2] = True
    m = depth_metrics(pred, gt, mask)
    assert m["n_gt"] == 8 and m["n_valid"] == 4 and m["completeness"] == 0.5 and m["mae"] == pytest.approx(3.0)
    m = depth_metrics(np.full((4, 4), np.nan), gt)
    assert m["n_valid"] == 0 and m["completeness"] == 0 and math.isnan(m["mae"]) and math.isnan(m["over_5mm"])
    m = depth_metrics(pred, np.full((4, 4), np.nan))
    assert m["n_gt"] == 0 and math.isnan(m["completeness"])
    err = error_map(pred, gt, mask)
    assert np.isnan(err[2:]).all() and np.allclose(err[1], 3.0)


def test_depth_metrics_bad_shapes():
    with pytest.raises(ValueError, match="prediction shape"):
        depth_metrics(np.zeros((3, 4)), np.zeros((4, 3)))
    with pytest.raises(ValueError, match="mask shape"):
        depth_metrics(np.zeros((3, 4)), np.zeros((3, 4)), np.zeros((4, 4), bool))


def test_format_table():
    t = format_table({"gc": {"mae": 1.23456, "over_1mm": 0.5, "n_valid": 10, "completeness": math.nan}})
    lines = t.splitlines()
    assert lines[0].startswith("| method") and "MAE mm" in lines[0] and ">5 mm %" in lines[0]
    cells = [c.strip() for c in lines[2].strip("|").split("|")]
    assert cells == ["gc", "1.235", "-", "-", "50.00%", "-", "-", "-", "10"]
    assert len({len(x) for x in lines}) == 1  # aligned


# ----------------------------------------------------------------------------------------------
# slwarp evaluate


def small_scan(with_gt=True) -> Scan:
    cam = Camera(40, 30, [[50, 0, 19.5], [0, 50, 14.5], [0, 0, 1]])
    R = look_at_rotation(np.array([50.0, 0, 0]), np.array([0, 0, 500.0]))
    proj = Projector(32, 24, [[40, 0, 15.5], [0, 40, 11.5], [0, 0, 1]], R=R, T=-R @ np.array([50.0, 0, 0]))
    rng = np.random.default_rng(0)
    gt = rng.uniform(500, 700, (30, 40)).astype(np.float32) if with_gt else None
    mask = np.ones((30, 40), bool)
    mask[:5] = False
    return Scan(cam, proj, rng.uniform(0, 1, (1, 30, 40)), np.ones((1, 24, 32)), ["white"], gt_depth=gt,
                mask=mask if with_gt else None)


@pytest.mark.parametrize("fmt", ["npy", "png"])
def test_cli_evaluate(tmp_path, capsys, fmt):
    small_scan().save(tmp_path / "scan")
    scan = load_scan(tmp_path / "scan")
    pred = scan.gt_depth + np.where(np.arange(40) % 2, 1.5, -0.3)[None, :]
    pred[10, :] = np.nan
    path = tmp_path / f"pred.{fmt}"
    if fmt == "npy":
        np.save(path, pred.astype(np.float32))
    else:
        write_depth_png(path, pred)
    assert cli_main(["evaluate", str(path), str(tmp_path / "scan"), "--out", str(tmp_path / "ev")]) == 0
    out = capsys.readouterr().out
    assert "MAE mm" in out and "pred." + fmt in out
    doc = json.loads((tmp_path / "ev" / "evaluation.json").read_text())
    assert doc["schema"] == METRICS_SCHEMA and doc["prediction"] == str(path) and doc["mask"] == "scan mask"
    ref = depth_metrics(pred if fmt == "npy" else np.round(pred * 10) / 10, scan.gt_depth, scan.mask)
    for k in ("mae", "rmse", "over_1mm", "completeness", "n_valid"):
        assert doc["metrics"][k] == pytest.approx(ref[k], rel=1e-5, abs=1e-6 if fmt == "npy" else 0.05)
    assert doc["metrics"]["n_gt"] == 25 * 40 and doc["metrics"]["completeness"] == pytest.approx(24 / 25)  # row 10 NaN
    assert (tmp_path / "ev" / "evaluation_error_map.png").is_file()
    # default: a file name no other command owns, beside the prediction (a reconstruction's metrics.json stays);
    # --no-mask counts every GT pixel
    (tmp_path / "metrics.json").write_text("{}")
    assert cli_main(["evaluate", str(path), str(tmp_path / "scan"), "--no-mask"]) == 0
    assert json.loads((tmp_path / "evaluation.json").read_text())["metrics"]["n_gt"] == 30 * 40
    assert (tmp_path / "metrics.json").read_text() == "{}"
    # --out FILE.json: the error map beside it
    assert cli_main(["evaluate", str(path), str(tmp_path / "scan"), "--out", str(tmp_path / "r" / "bunny.json")]) == 0
    assert json.loads((tmp_path / "r" / "bunny.json").read_text())["schema"] == METRICS_SCHEMA
    assert (tmp_path / "r" / "bunny_error_map.png").is_file()


def test_cli_evaluate_never_writes_into_the_scan_folder(tmp_path, capsys):
    small_scan().save(tmp_path / "scan")
    gt = tmp_path / "scan" / "gt_depth.npy"
    np.save(gt, load_scan(tmp_path / "scan").gt_depth.astype(np.float32))
    before = sorted(p.name for p in (tmp_path / "scan").iterdir())
    assert cli_main(["evaluate", str(gt), str(tmp_path / "scan")]) == 2
    assert "is the scan folder" in capsys.readouterr().err
    assert sorted(p.name for p in (tmp_path / "scan").iterdir()) == before


def test_one_metrics_schema():
    m = {"mae": 1.0}
    doc = metrics_document(m, method="gc", scan="s", frames=["a"], mask="scan mask", params={"x": 1})
    assert doc == {"schema": METRICS_SCHEMA, "method": "gc", "prediction": None, "scan": "s", "frames": ["a"],
                   "mask": "scan mask", "params": {"x": 1}, "metrics": {"mae": 1.0}}


def test_cli_evaluate_bad_input(tmp_path, capsys):
    small_scan().save(tmp_path / "scan")
    small_scan(with_gt=False).save(tmp_path / "nogt")
    np.save(tmp_path / "pred.npy", np.full((30, 40), 600.0, np.float32))
    np.save(tmp_path / "wrong.npy", np.full((31, 40), 600.0, np.float32))
    (tmp_path / "bad.png").write_bytes(b"not a png")
    cases = [
        (["evaluate", str(tmp_path / "missing.npy"), str(tmp_path / "scan")], "prediction not found"),
        (["evaluate", str(tmp_path / "wrong.npy"), str(tmp_path / "scan")], "depth map is 40x31"),
        (["evaluate", str(tmp_path / "pred.npy"), str(tmp_path / "nogt")], "no ground-truth depth"),
        (["evaluate", str(tmp_path / "bad.png"), str(tmp_path / "scan")], "unreadable or corrupt"),
        (["evaluate", str(tmp_path / "pred.npy"), str(tmp_path / "nowhere")], "scan not found"),
        (["evaluate", str(tmp_path / "pred.npy"), str(tmp_path / "scan"), "--out", str(tmp_path / "pred.npy")],
         "is a file"),
    ]
    for argv, msg in cases:
        assert cli_main(argv) == 2
        err = capsys.readouterr().err
        assert msg in err and len(err.strip().splitlines()) == 1


def test_quadric_rms_removes_a_smooth_bend_and_keeps_the_local_error():
    """A board bent by 1 mm (a quadratic height field over a tilted plane): the plane's RMS holds the bend, the
    quadric's does not; white noise of 0.2 mm stays in both."""
    import numpy as np

    from slwarp.evaluation.metrics import plane_rms, quadric_rms

    rng = np.random.default_rng(0)
    u, v = np.meshgrid(np.linspace(-100, 100, 120), np.linspace(-80, 80, 100))
    bend = 1.0 * ((u / 100) ** 2 + 0.5 * (u / 100) * (v / 80))
    for noise in (0.0, 0.2):
        h = bend + noise * rng.standard_normal(u.shape)
        tilt = np.array([[1, 0, 0.3], [0, 1, -0.2], [0, 0, 1.0]])
        pts = np.stack([u, v, 1200 + h], -1).reshape(-1, 3) @ tilt.T
        assert plane_rms(pts)[0] > 0.25
        assert quadric_rms(pts) == pytest.approx(noise, abs=0.01)
    assert np.isnan(quadric_rms(np.zeros((5, 3))))
