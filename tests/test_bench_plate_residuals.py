"""bench.plate_residuals: a plate's residual to its plane, split by spatial scale."""
import numpy as np
import pytest

from bench.plate_residuals import by_scale, main, plate_residual
from slwarp.scans.scanner import Camera


def _camera(w=96, h=80, f=200.0):
    return Camera(width=w, height=h, K=np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]]), dist=np.zeros(5))


def test_a_tilted_plane_leaves_no_residual_and_a_wave_stays_at_its_scale():
    cam = _camera()
    v, u = np.mgrid[0:80, 0:96].astype(np.float64)
    # a plane z = 1000 + 0.3 x_mm (x_mm = (u - cx) z / f): depth along each ray
    xn = (u - 48) / 200.0
    plane = 1000.0 / (1.0 - 0.3 * xn)
    region = np.zeros((80, 96), bool)
    region[10:70, 10:86] = True
    r = plate_residual(plane, region, cam)
    assert np.isnan(r[~region]).all() and np.nanmax(np.abs(r)) < 1e-3  # float32 points
    # a ripple of 0.5 mm amplitude along the rows, period 40 px: large-scale, nothing within 5x5
    wave = 1000.0 + 0.5 * np.sin(2 * np.pi * v / 40.0)
    s = by_scale(plate_residual(wave, region, cam))
    assert 0.3 < s["rms"] < 0.4 and s["hp2"] < 0.05 < 0.2 < s["hp16"]
    assert s["row_mean_std"] > 0.3 and s["col_mean_std"] < 0.02
    # pixel noise: all of it within 5x5
    noisy = 1000.0 + np.random.default_rng(0).normal(0, 0.2, (80, 96))
    s = by_scale(plate_residual(noisy, region, cam))
    assert abs(s["hp2"] - s["rms"]) < 0.03 and abs(s["rms"] - 0.2) < 0.02


def test_main_names_a_missing_capture_or_map(tmp_path):
    with pytest.raises(SystemExit, match="no prepared capture"):
        main([str(tmp_path / "d.npy"), "--capture", "1", "--data", str(tmp_path)])
    (tmp_path / "capture_1").mkdir()
    np.savez(tmp_path / "capture_1" / "reference.npz", region=np.ones((2, 2), bool))
    with pytest.raises(SystemExit, match="no such depth map"):
        main([str(tmp_path / "d.npy"), "--capture", "1", "--data", str(tmp_path)])
