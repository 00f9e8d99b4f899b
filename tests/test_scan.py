"""Scans on disk: native save/load, the NeSS and procam importers, frame selection, and one test per
bad input (each must raise ScanError naming the file and the problem, and exit 2 from the CLI)."""
import dataclasses
import shutil

import cv2
import numpy as np
import pytest
import yaml

from slwarp.cli import main as cli_main
from slwarp.scans.patterns import gray_code
from slwarp.evaluation.outputs import write_depth_png
from slwarp.scans.scan import Scan, ScanError, load_scan, read_depth
from slwarp.scans.scanner import Camera, Projector, look_at_rotation


def tiny_scan(n=3, with_gt=True) -> Scan:
    rng = np.random.default_rng(0)
    cam = Camera(64, 48, [[60, 0, 31.5], [0, 60, 23.5], [0, 0, 1]], [0.01, 0, 0, 0, 0])
    R = look_at_rotation(np.array([50.0, 0, 0]), np.array([0, 0, 500.0]))
    proj = Projector(80, 60, [[70, 0, 39.5], [0, 70, 29.5], [0, 0, 1]], R=R, T=-R @ np.array([50.0, 0, 0]))
    pats = gray_code(80, 60, n)
    imgs = rng.uniform(0, 1, (n, 48, 64)).astype(np.float32)
    gt = rng.uniform(400, 900, (48, 64)).astype(np.float32) if with_gt else None
    if gt is not None:
        gt[:3] = np.nan
    mask = rng.uniform(size=(48, 64)) > 0.3
    return Scan(cam, proj, imgs, pats.patterns, pats.names, depth_range=(300.0, 1000.0), gt_depth=gt, mask=mask)


@pytest.fixture
def native(tmp_path):
    folder = tmp_path / "scan"
    tiny_scan().save(folder)
    return folder


def edit_yaml(folder, fn):
    doc = yaml.safe_load((folder / "scan.yaml").read_text())
    fn(doc)
    (folder / "scan.yaml").write_text(yaml.safe_dump(doc))


def test_native_round_trip(native):
    ref = tiny_scan()
    scan = load_scan(native)
    assert scan.names == ref.names
    assert np.abs(scan.images - ref.images).max() <= 0.5 / 255 + 1e-6
    assert np.array_equal(scan.patterns, ref.patterns)
    assert np.allclose(scan.camera.K, ref.camera.K) and np.allclose(scan.projector.R, ref.projector.R)
    assert np.array_equal(np.isnan(scan.gt_depth), np.isnan(ref.gt_depth))
    assert np.nanmax(np.abs(scan.gt_depth - ref.gt_depth)) < 1e-3
    assert np.array_equal(scan.mask, ref.mask)
    assert scan.depth_range == (300.0, 1000.0)


def test_16bit_and_color_images_accepted(native):
    img = (np.random.default_rng(1).uniform(size=(48, 64)) * 65535).astype(np.uint16)
    cv2.imwrite(str(native / "images/000_gc_col_b0.png"), img)
    color = np.zeros((48, 64, 3), np.uint8)
    color[..., 1] = 200  # pure green
    cv2.imwrite(str(native / "images/001_gc_col_b1.png"), color)
    scan = load_scan(native)
    assert np.allclose(scan.images[0], img / 65535.0, atol=1e-6)
    assert np.allclose(scan.images[1], round(0.587 * 200) / 255.0, atol=1.5 / 255)


def test_frame_selection(native):
    scan = load_scan(native)
    assert scan.select("gc_col_b2,0").names == ["gc_col_b2", "gc_col_b0"]
    assert scan.select("gc_col_b*").names == scan.names
    assert scan.select("1:").names == scan.names[1:]
    assert load_scan(native, frames=[0, "gc_col_b1"]).names == ["gc_col_b0", "gc_col_b1"]
    with pytest.raises(ScanError, match="no frame matches 'zebra'"):
        scan.select("zebra")
    with pytest.raises(ScanError, match="out of range"):
        scan.select(7)


def test_depth_png_round_trip(tmp_path):
    d = np.array([[500.04, np.nan], [1234.56, 0.0]], np.float32)
    write_depth_png(tmp_path / "d.png", d)
    back = read_depth(tmp_path / "d.png")
    assert abs(back[0, 0] - 500.0) < 1e-3 and abs(back[1, 0] - 1234.6) < 1e-3
    assert np.isnan(back[0, 1]) and np.isnan(back[1, 1])


def test_procam_layout(chessboard_path):
    scan = load_scan(chessboard_path)
    assert len(scan) == 42
    assert (scan.camera.width, scan.camera.height) == (1280, 1024)
    assert (scan.projector.width, scan.projector.height) == (1024, 768)
    assert scan.names[0] == "gc_col_b0" and scan.names[20] == "gc_row_b0" and scan.names[-2:] == ["white", "black"]
    assert 280 < scan.projector.baseline < 300
    assert scan.image("white").mean() > scan.image("black").mean() + 0.1


def test_info_cli_on_real_capture(chessboard_path, capsys):
    assert cli_main(["info", str(chessboard_path)]) == 0
    out = capsys.readouterr().out
    assert "frames: 42" in out and "1280x1024" in out and "1024x768" in out


def write_ness(folder, scan: Scan):
    (folder / "img").mkdir(parents=True)
    (folder / "pat").mkdir()
    (folder / "gt").mkdir()
    c, p = scan.camera, scan.projector
    cfg = "\n".join([
        "[RawCalib]",
        f"img_size = {c.width},{c.height}",
        f"pat_size = {p.width},{p.height}",
        f"img_intrin = {c.fx},{c.fy},{c.cx},{c.cy}",
        f"pat_intrin = {p.fx},{p.fy},{p.cx},{p.cy}",
        "ext_rot = " + ",".join(repr(float(x)) for x in p.R.ravel()),
        "ext_tran = " + ",".join(repr(float(x)) for x in p.T),
        "z_range = 300.0,1000.0",
    ])
    (folder / "config.ini").write_text(cfg + "\n")
    for i in range(len(scan)):
        cv2.imwrite(str(folder / "img" / f"img_{i}.png"), (scan.images[i] * 255).round().astype(np.uint8))
        cv2.imwrite(str(folder / "pat" / f"pat_{i}.png"), (scan.patterns[i] * 255).round().astype(np.uint8))
    write_depth_png(folder / "gt" / "depth.png", scan.gt_depth)
    cv2.imwrite(str(folder / "gt" / "mask_occ.png"), scan.mask.astype(np.uint8) * 255)


def test_ness_layout(tmp_path):
    ref = dataclasses.replace(tiny_scan(), camera=Camera(64, 48, [[60, 0, 31.5], [0, 60, 23.5], [0, 0, 1]]))
    write_ness(tmp_path / "ness", ref)
    scan = load_scan(tmp_path / "ness")
    assert scan.names == ["0", "1", "2"]  # tags outside the authors' grammar: kept, in natural order, no role
    assert scan.roles == [None, None, None] and scan.select("1").names == ["1"]  # a name before an index
    assert np.allclose(scan.projector.R, ref.projector.R, atol=1e-9)
    assert np.allclose(scan.projector.T, ref.projector.T)
    assert scan.depth_range == (300.0, 1000.0)
    assert np.nanmax(np.abs(scan.gt_depth - ref.gt_depth)) <= 0.051
    assert np.array_equal(scan.mask, ref.mask)
    assert np.array_equal(scan.patterns, ref.patterns)


# --- bad input: one test each ----------------------------------------------------------------


def expect_error(folder, match, capsys=None):
    with pytest.raises(ScanError, match=match) as e:
        load_scan(folder)
    if capsys is not None:
        assert cli_main(["info", str(folder)]) == 2
        err = capsys.readouterr().err
        assert "error:" in err and "Traceback" not in err
    return str(e.value)


def test_missing_scan_yaml(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    msg = expect_error(tmp_path / "empty", "missing scan.yaml", capsys)
    assert str(tmp_path / "empty") in msg


def test_missing_image(native, capsys):
    (native / "images/001_gc_col_b1.png").unlink()
    msg = expect_error(native, "not found", capsys)
    assert "001_gc_col_b1.png" in msg


def test_corrupt_image(native, capsys):
    (native / "images/002_gc_col_b2.png").write_bytes(b"\x89PNG\r\n garbage")
    msg = expect_error(native, "unreadable or corrupt", capsys)
    assert "002_gc_col_b2.png" in msg


def test_image_count_differs_from_pattern_count(tmp_path, capsys):
    scan = tiny_scan()
    write_ness(tmp_path / "n", scan)
    (tmp_path / "n" / "img" / "img_2.png").unlink()
    expect_error(tmp_path / "n", r"image count != pattern count", capsys)


def test_image_size_differs_from_camera(native, capsys):
    cv2.imwrite(str(native / "images/000_gc_col_b0.png"), np.zeros((40, 64), np.uint8))
    msg = expect_error(native, r"image size 64x40 != camera size 64x48", capsys)
    assert "000_gc_col_b0.png" in msg


def test_pattern_size_differs_from_projector(native, capsys):
    cv2.imwrite(str(native / "patterns/gc_col_b1.png"), np.zeros((60, 81), np.uint8))
    msg = expect_error(native, r"pattern size 81x60 != projector size 80x60", capsys)
    assert "gc_col_b1.png" in msg


def test_non_finite_intrinsics(native, capsys):
    edit_yaml(native, lambda d: d["camera"]["K"][0].__setitem__(0, float("nan")))
    msg = expect_error(native, "non-finite", capsys)
    assert "scan.yaml" in msg


def test_singular_intrinsics(native, capsys):
    edit_yaml(native, lambda d: d["projector"].__setitem__("K", [[0, 0, 0], [0, 0, 0], [0, 0, 1]]))
    expect_error(native, "singular", capsys)


def test_rotation_not_orthonormal(native, capsys):
    edit_yaml(native, lambda d: d["extrinsics"]["R"][0].__setitem__(0, d["extrinsics"]["R"][0][0] + 0.01))
    expect_error(native, "not a rotation", capsys)


def test_rotation_with_negative_determinant(native, capsys):
    edit_yaml(native, lambda d: d["extrinsics"].__setitem__("R", [[1, 0, 0], [0, 1, 0], [0, 0, -1]]))
    expect_error(native, "det = -1", capsys)


def test_empty_frame_list(native, capsys):
    edit_yaml(native, lambda d: d.__setitem__("frames", []))
    expect_error(native, "frame list is empty", capsys)


def test_procam_count_mismatch(tmp_path, chessboard_path):
    dst = tmp_path / "procam"
    shutil.copytree(chessboard_path, dst)
    (dst / "capture_0").chmod(0o755)  # the shared data is read-only
    for f in (dst / "capture_0").glob("graycode_41.png"):
        f.chmod(0o644)
        f.unlink()
    expect_error(dst, r"image count \(41\) != pattern count \(42\)")
