"""The classical decoders on every rig geometry: gc-interp follows the direction in which the code changes, the
triangulation follows the baseline, the phase methods take the axis that carries depth."""
from dataclasses import replace

import numpy as np
import pytest

from slwarp.decode import (baseline_alignment, choose_triangulation, decode, reconstruct_depth, triangulate,
                           triangulate_rays)
from slwarp.decode.gray import HOW_INTERPOLATED, GrayTable, code_gradient, interpolate_stripes
from slwarp.evaluation.metrics import depth_metrics
from slwarp.scans.patterns import gray_code
from slwarp.sim.rigs import GEOMETRIES, _build, make_rig, rig_name
from slwarp.sim.scenes import build_scene
from slwarp.sim.simulate import SimOptions, simulate, simulate_scene

# ----------------------------------------------------------------------------------------------
# interpolation along the code gradient, on synthetic stripes at any angle


def stripe_field(angle_deg: float, shape=(90, 110), px_per_camera_px: float = 1.7, size: int = 640, bits: int = 7):
    """A decoded Gray code whose projector position grows linearly along direction `angle_deg` of the camera
    image (0: along rows, 90: down columns): (true position [H, W], stripe [H, W], signal [n, H, W], table).
    Each bit's signal is its pattern blurred by a Gaussian of 1.5 projector px (the camera pixel's footprint
    and defocus), sampled at the position: it crosses zero exactly at the stripe edges (Gray code bits are
    square waves of equal on and off runs), smoothly enough for a crossing between two pixels to be located."""
    import cv2

    H, W = shape
    y, x = np.mgrid[0:H, 0:W].astype(np.float64)
    a = np.radians(angle_deg)
    u = 150.0 + px_per_camera_px * ((x - W / 2) * np.cos(a) + (y - H / 2) * np.sin(a)) + 0.3 * np.sin(x / 17.0)
    pats = gray_code(size, 2, bits).patterns
    table = GrayTable.from_patterns(pats, "col")
    prof = cv2.GaussianBlur(pats[:, 0, :].astype(np.float64), (0, 0), sigmaX=1.5, sigmaY=1e-6,
                            borderType=cv2.BORDER_REPLICATE)
    signal = np.stack([np.interp(u, np.arange(size), p) * 2.0 - 1.0 for p in prof])
    code = ((signal > 0).astype(np.int64) * (1 << np.arange(bits - 1, -1, -1))[:, None, None]).sum(0)
    return u, table.lut[code], signal, table


@pytest.mark.parametrize("angle", [0.0, 30.0, 45.0, 60.0, 90.0, 135.0, 180.0, 270.0])
def test_interpolation_follows_the_code_gradient_at_any_angle(angle):
    u, stripe, signal, table = stripe_field(angle)
    pos, how, info = interpolate_stripes(stripe, signal, table)
    inter = how == HOW_INTERPOLATED
    assert inter.mean() > 0.8
    err = np.abs(pos - u)[inter]
    # the position bends slightly (the sin term): linear interpolation across a 5 px stripe is off by < 0.05 px
    assert err.max() < 0.1, (angle, err.max())
    # the weight of camera rows: cos^4 / (cos^4 + sin^4) of the gradient's angle to them (1 along rows, 0 down
    # columns, 1/2 at 45 deg)
    c4, s4 = np.cos(np.radians(angle)) ** 4, np.sin(np.radians(angle)) ** 4
    w = info["weight_row"][stripe >= 0]
    assert np.median(w) == pytest.approx(c4 / (c4 + s4), abs=0.08)


def test_interpolation_along_rows_alone_fails_on_stripes_parallel_to_rows():
    """The reason for the gradient: stripes that run along camera rows (a projector rolled 90 deg) cannot be
    interpolated along rows; the gradient sends them down the columns."""
    from slwarp.decode.gray import interpolate_transitions

    u, stripe, signal, table = stripe_field(90.0)
    along_rows, how_rows = interpolate_transitions(stripe, signal, table, along=1)
    assert (how_rows == HOW_INTERPOLATED).mean() < 0.05  # no row crosses two stripe edges
    pos, how, _ = interpolate_stripes(stripe, signal, table)
    assert np.nanmean(np.abs(along_rows - u)) > 5 * np.nanmean(np.abs(pos - u))


def test_code_gradient_cancels_flicker():
    """Noise that flickers across one stripe edge (+1, -1, +1 along a row) adds nothing to the gradient."""
    stripe = np.repeat(np.arange(12)[:, None], 40, axis=1)  # stripes along rows: the code grows down columns
    stripe[5, ::2] = 6  # row 5 flickers between stripes 5 and 6
    gx, gy = code_gradient(stripe, radius=4)
    assert np.all(gy > 0) and np.abs(gx[2:9, 4:-4]).max() <= 1


# ----------------------------------------------------------------------------------------------
# triangulation from the rig


def test_triangulation_choice_follows_the_baseline():
    assert baseline_alignment(make_rig("default")[1])["col"] > 0.999
    assert baseline_alignment(make_rig("vertical")[1])["row"] > 0.999
    assert baseline_alignment(make_rig("rolled")[1])["col"] > 0.999  # rolled: its columns run along the baseline
    a = baseline_alignment(make_rig("oblique")[1])
    assert a["col"] == pytest.approx(a["row"], abs=0.03)
    for geometry, both in [("default", "col"), ("vertical", "row"), ("rolled", "col"), ("oblique", "both")]:
        proj = make_rig(geometry)[1]
        assert choose_triangulation(proj, True, False) == "col"  # only one coordinate: its plane
        assert choose_triangulation(proj, False, True) == "row"
        assert choose_triangulation(proj, True, True) == both


@pytest.mark.parametrize("geometry", list(GEOMETRIES))
def test_both_coordinates_give_exact_depth(geometry):
    """Exact correspondences through both distorted lenses: the least-squares point on the camera ray is the
    surface point, with no residual."""
    cam, proj = make_rig(rig_name(geometry, small=True))
    uv = cam.pixel_grid()
    x, y = uv[..., 0] / cam.width - 0.5, uv[..., 1] / cam.height - 0.5
    depth = 760.0 * (1 + 0.1 * x - 0.15 * y) - 60.0 * np.exp(-(x**2 + y**2) / 0.05)
    d = cam.pixel_to_ray(uv)
    X = d * (depth / d[..., 2])[..., None]
    puv = proj.project_camera_points(X)
    ok = proj.in_image(puv) & np.isfinite(puv).all(-1)
    puv[~ok] = np.nan
    pts, resid = triangulate_rays(cam, proj, puv[..., 0], puv[..., 1])
    assert ok.mean() > 0.5
    assert np.abs(pts[..., 2] - depth)[ok].max() < 1e-3 and np.nanmax(resid[ok]) < 1e-6
    z, _, info = triangulate(cam, proj, puv[..., 0], puv[..., 1])
    assert info["mode"] == ("both" if geometry == "oblique" else "row" if geometry == "vertical" else "col")
    assert info["alignment"] > 0.99 or geometry == "oblique"
    assert np.abs(z - depth)[ok].max() < 1e-3


# ----------------------------------------------------------------------------------------------
# GC(7)-interp on every rig, against the horizontal rig's error


def gc7_mae(scan, axis: str) -> float:
    depth, _, dec = reconstruct_depth(scan, "gc-interp", frames=f"gray:{axis}:bit=0-6:noinv")
    assert dec.extra["triangulation"] == axis
    return depth_metrics(depth, scan.gt_depth, scan.mask)["mae"]


@pytest.fixture(scope="module")
def rig_scans():
    """Small-rig scans of two scenes with 7-bit column and row codes, lens distortion and noise on."""
    return {(g, s): simulate_scene(s, "gray7+gray7_row", rig_name(g, small=True), SimOptions(seed=1), device="cpu")
            for g in GEOMETRIES for s in ("bunny", "torus")}


# the codes that carry depth on each geometry (column codes on the default and rolled rigs, row codes on the
# vertical one, both on the oblique one)
DEPTH_CODES = [("default", "col"), ("vertical", "row"), ("oblique", "col"), ("oblique", "row"), ("rolled", "col")]


@pytest.mark.parametrize("geometry,axis", DEPTH_CODES)
@pytest.mark.parametrize("scene", ["bunny", "torus"])
def test_gc7_interp_on_every_rig_within_1_5x_of_horizontal(rig_scans, geometry, axis, scene):
    reference = gc7_mae(rig_scans[("default", scene)], "col")
    mae = gc7_mae(rig_scans[(geometry, scene)], axis)
    print(f"{scene}: GC(7)-interp {geometry}/{axis} {mae:.3f} mm, default/col {reference:.3f} mm")
    assert reference < 1.0
    assert mae <= 1.5 * reference


def test_oblique_rig_uses_both_codes(rig_scans):
    """On the 45 deg baseline, both codes carry depth: decoding both and triangulating with both beats either."""
    scan = rig_scans[("oblique", "bunny")]
    depth, _, dec = reconstruct_depth(scan, "gc-interp")
    assert dec.extra["triangulation"] == "both"
    mae = depth_metrics(depth, scan.gt_depth, scan.mask)["mae"]
    assert mae < 0.9 * min(gc7_mae(scan, "col"), gc7_mae(scan, "row"))


def test_diagonal_stripes_in_the_camera():
    """A projector rolled 45 deg on the oblique baseline: its column stripes cross the camera image at 45 deg
    (the code gradient runs diagonally); GC(7)-interp stays as accurate as on the default rig."""
    g = replace(GEOMETRIES["oblique"], projector_center=(106.07, 106.07, 0.0), roll_deg=45.0)
    cam, proj = _build(g, small=True)
    assert baseline_alignment(proj)["col"] > 0.99
    from slwarp.scans.patterns import named_set

    scene = build_scene("bunny")
    diag = simulate(scene, cam, proj, named_set("gray7", proj.width, proj.height), SimOptions(seed=1),
                    depth_range=(450.0, 1100.0), device="cpu")
    dec = decode(diag, "gc-interp")
    w = dec.extra["weight_row_col"][diag.mask]
    assert 0.3 < np.median(w) < 0.7  # diagonal: both camera axes used
    cam0, proj0 = make_rig("small")
    ref = simulate(scene, cam0, proj0, named_set("gray7", proj0.width, proj0.height), SimOptions(seed=1),
                   depth_range=(450.0, 1100.0), device="cpu")
    assert gc7_mae(diag, "col") <= 1.5 * gc7_mae(ref, "col")


# ----------------------------------------------------------------------------------------------
# phase methods and CGC take the axis that carries depth


def test_phase_methods_pick_the_depth_axis():
    """On the vertical rig, with column and row sets in the scan, the phase methods decode rows; with column
    sets only, they decode columns (and triangulation says how little depth those carry)."""
    both = simulate_scene("spheres", "npmp6+npmp6_row+cgc7+cgc7_row", "small-vertical", SimOptions(seed=2), device="cpu")
    for method in ("npmp", "cgc"):
        depth, _, dec = reconstruct_depth(both, method)
        assert dec.row is not None and dec.col is None and dec.extra["axis"] == "row"
        assert dec.extra["triangulation"] == "row" and dec.extra["baseline_alignment"] > 0.99
        m = depth_metrics(depth, both.gt_depth, both.mask)
        assert m["mae"] < 3.0 and m["completeness"] > 0.8, (method, m)
    cols = both.select("phase:col,gray:col")
    _, _, dec = reconstruct_depth(cols, "npmp")
    assert dec.extra["axis"] == "col" and dec.extra["baseline_alignment"] < 0.01
