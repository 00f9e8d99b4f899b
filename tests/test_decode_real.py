"""The real capture (../shared/data/procam_chessboard): OpenCV's Gray code decoded from its own pattern
images, triangulated, gives the chessboard plate as a plane.

Reference: an independent implementation measured about 1.25 mm RMS to the fitted plane; the issue asks
for at most 1.5 mm. Our full Gray code decode with default thresholds measures 1.43 mm (row plane; 1.42 mm
by the ray-ray midpoint; about 12 mm by the column plane, which nearly contains the camera rays on this vertical
baseline) and gc-interp 0.69 mm. The difference to 1.25 mm is which pixels count: with OpenCV's thresholds
(white - black > 40 grey levels and every |bit - inverse| >= 5) our decoder keeps 45% of the board and
measures 1.29 mm; the default keeps more of the board's dark squares (white - black of 8 to 12 grey levels).
"""
import json

import numpy as np
import pytest

from slwarp.cli import main as cli_main
from slwarp.decode import decode, reconstruct_depth, triangulate
from slwarp.decode.gray import GrayTable
from slwarp.scans.scan import load_scan


@pytest.fixture(scope="module")
def capture(chessboard_path):
    return load_scan(chessboard_path)


@pytest.fixture(scope="module")
def board(capture):
    """[H, W] bool: the quadrilateral spanned by the outer ones of the 9x7 inner chessboard corners."""
    import cv2

    white = np.clip(np.rint(capture.image("white") * 255), 0, 255).astype(np.uint8)
    found, corners = cv2.findChessboardCorners(white, (9, 7))
    assert found, "OpenCV does not find the 9x7 chessboard in the white image"
    c = corners.reshape(7, 9, 2)
    quad = np.round([c[0, 0], c[0, -1], c[-1, -1], c[-1, 0]]).astype(np.int32)
    mask = np.zeros(white.shape, np.uint8)
    cv2.fillConvexPoly(mask, quad, 1)
    assert mask.sum() > 100_000
    return mask.astype(bool)


def plane_rms(points: np.ndarray, region: np.ndarray) -> tuple[float, int]:
    """RMS distance (mm) of the finite points inside `region` to their least-squares plane (SVD)."""
    P = points[region]
    P = P[np.isfinite(P).all(1)]
    c = P.mean(0)
    normal = np.linalg.svd(P - c, full_matrices=False)[2][2]
    return float(np.sqrt((((P - c) @ normal) ** 2).mean())), len(P)


def test_code_tables_from_opencv_patterns(capture):
    cols = [f"gc_col_b{k}" for k in range(10)]
    rows = [f"gc_row_b{k}" for k in range(10)]
    pat = {n: capture.patterns[capture.names.index(n)] for n in cols + rows}
    t = GrayTable.from_patterns(np.stack([pat[n] for n in cols]), "col", cols)
    assert len(t.start) == 1024 and t.max_width == 1 and np.allclose(t.center, np.arange(1024))
    t = GrayTable.from_patterns(np.stack([pat[n] for n in rows]), "row", rows)
    assert len(t.start) == 768 and np.allclose(t.center, np.arange(768))
    t7 = GrayTable.from_patterns(np.stack([pat[n] for n in cols[:7]]), "col")  # the 7 most significant bits
    assert len(t7.start) == 128 and np.allclose(t7.center, np.arange(128) * 8 + 3.5)


def test_full_gray_code_gives_plane(capture, board):
    depth, points, dec = reconstruct_depth(capture, "gc")
    assert dec.extra["bits_col"] == 10 and dec.extra["bits_row"] == 10
    assert dec.extra["inverses_col"] and dec.extra["inverses_row"]
    assert dec.extra["triangulation"] == "row"  # the baseline is mostly vertical
    rms, n = plane_rms(points, board)
    print(f"real capture, full Gray code, row plane: plane RMS {rms:.3f} mm over {n} points")
    assert n > 0.6 * board.sum()
    assert rms <= 1.5
    assert 1500 < np.nanmedian(depth[board]) < 1700  # the plate is about 1.6 m away
    # the ray-ray midpoint from both codes agrees
    _, pts_mid, info = triangulate(capture.camera, capture.projector, dec.col, dec.row, "midpoint")
    rms_mid, _ = plane_rms(pts_mid, board)
    print(f"real capture, full Gray code, midpoint: plane RMS {rms_mid:.3f} mm")
    assert rms_mid <= 1.5 and np.nanmedian(info["gap"][board]) < 1.0


def test_interpolated_gray_code_is_flatter(capture, board):
    dec = decode(capture, "gc-interp")
    _, points, _ = triangulate(capture.camera, capture.projector, dec.col, dec.row)
    rms, _ = plane_rms(points, board)
    print(f"real capture, gc-interp: plane RMS {rms:.3f} mm")
    assert rms <= 1.0


def test_cli_decode_real_capture(chessboard_path, tmp_path, capsys):
    assert cli_main(["decode", str(chessboard_path), "--method", "gc", "--triangulation", "midpoint",
                     "--out", str(tmp_path / "gc")]) == 0
    out = tmp_path / "gc"
    for f in ("depth.npy", "depth.png", "depth_color.png", "points.ply", "decode.json"):
        assert (out / f).is_file()
    assert not (out / "metrics.json").exists()  # no ground truth
    doc = json.loads((out / "decode.json").read_text())
    assert doc["triangulation"] == "midpoint" and doc["valid_share"] > 0.8
    assert cli_main(["decode", str(chessboard_path), "--method", "cgc", "--out", str(tmp_path / "x")]) == 2
    # the phase methods look for the rows' frames first on this vertical baseline, and name those
    err = capsys.readouterr().err
    assert "method cgc needs Gray code bits 0..2 along row (gray:row:bit=0-2)" in err
    assert "the scan has: gray:col:bit=0-9 (+inv), gray:row:bit=0-9 (+inv), white, black" in err


def test_seven_row_bits_give_a_plane(capture, board):
    """GC(7)-interp of the 7 most significant row bits, no inverses (the frames the neural method trains on):
    triangulated with the row plane by default, the plate is a plane within a few mm (2.37 mm measured, 9.97
    at the stripe centres); the 7 column bits, which see little of this vertical baseline, are far worse."""
    depth, points, dec = reconstruct_depth(capture, "gc-interp", frames="gray:row:bit=0-6:noinv")
    assert dec.frames == [f"gc_row_b{k}" for k in range(7)] and dec.extra["triangulation"] == "row"
    rms, n = plane_rms(points, board)
    print(f"real capture, GC(7)-interp of the row bits: plane RMS {rms:.3f} mm")
    assert n > 0.55 * board.sum() and rms <= 3.0
    _, points_col, dec_col = reconstruct_depth(capture, "gc-interp", frames="gray:col:bit=0-6:noinv")
    assert dec_col.extra["triangulation"] == "col" and dec_col.extra["baseline_alignment"] < 0.2
    assert plane_rms(points_col, board)[0] > 3 * rms


def test_triangulated_points_reproject_through_opencv_onto_the_decoded_codes(capture, chessboard_path):
    """The plate's smooth bend (plane RMS 0.69 mm, about a quadric 0.51 mm for the full gc-interp decode; docs/
    accuracy.md section 14) is the calibration's, not our geometry's: every triangulated point, projected by
    OpenCV's own projectPoints with the file's raw matrices and distortion, lands on its camera pixel and on the
    projector row its codes decoded."""
    import cv2

    depth, points, dec = reconstruct_depth(capture, "gc-interp")
    assert dec.extra["triangulation"] == "row"
    ok = np.isfinite(depth)
    assert ok.sum() > 500_000
    fs = cv2.FileStorage(str(chessboard_path / "calibration_result.xml"), cv2.FILE_STORAGE_READ)

    def mat(*keys):  # the first key the file holds (this version of the tool spells rotation "roration")
        return next(fs.getNode(k).mat() for k in keys if not fs.getNode(k).empty())

    X = points[ok].reshape(-1, 1, 3).astype(np.float64)
    cam, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), mat("cam_int"), mat("cam_dist"))
    prj, _ = cv2.projectPoints(X, cv2.Rodrigues(mat("rotation", "roration"))[0], mat("translation"), mat("proj_int"),
                               mat("proj_dist"))
    v, u = np.nonzero(ok)
    assert np.abs(cam.reshape(-1, 2) - np.stack([u, v], -1)).max() < 1e-3
    assert np.abs(prj.reshape(-1, 2)[:, 1] - np.asarray(dec.row)[ok]).max() < 1e-3
