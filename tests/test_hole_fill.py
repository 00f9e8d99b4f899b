"""The hole fill at extraction (slwarp.neural.extraction.surface.fill_pinholes and its stage, hole_fill): a pixel
without depth inside a smooth surface takes the depth of the plane through its neighbours; a hole beside a depth
edge, a larger hole and a pixel outside the region stay holes."""
import numpy as np
import pytest

from slwarp.neural.config import ConfigError, preset
from slwarp.neural.extraction.surface import fill_pinholes
from slwarp.scans.scanner import Camera

CAMERA = Camera(width=40, height=30, K=np.array([[500.0, 0, 19.5], [0, 500.0, 14.5], [0, 0, 1]]))


def _slanted(H=30, W=40):
    """[H, W] float32 mm: a slanted plane, 2 mm a column and 1 mm a row around 800 mm."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    return (800.0 + 2.0 * u + 1.0 * v).astype(np.float32)


def test_single_and_paired_pinholes_take_the_planes_depth():
    plane = _slanted()
    depth = plane.copy()
    holes = [(5, 5), (10, 20), (10, 21), (20, 8)]  # (10, 20) and (10, 21): a hole of two pixels
    for y, x in holes:
        depth[y, x] = np.nan
    out, filled = fill_pinholes(depth, CAMERA, None, 6, 0.5)
    assert filled.sum() == len(holes)
    for y, x in holes:
        assert filled[y, x]
        assert out[y, x] == pytest.approx(plane[y, x], abs=1e-3)
    np.testing.assert_array_equal(out[~filled], depth[~filled])


def test_a_hole_beside_a_depth_edge_a_large_hole_and_one_outside_the_region_stay():
    depth = _slanted()
    depth[:, 20:] += 30.0  # a depth edge between columns 19 and 20: 30 mm, about 19 footprints
    depth[12, 20] = np.nan  # beside the edge: its neighbours lie on two surfaces
    depth[3:6, 3:6] = np.nan  # 3 x 3: no pixel of it has 6 neighbours with depth
    depth[25, 30] = np.nan  # a pinhole outside the region
    region = np.ones(depth.shape, bool)
    region[25, 30] = False
    out, filled = fill_pinholes(depth, CAMERA, region, 6, 0.5)
    assert not filled.any()
    np.testing.assert_array_equal(np.isnan(out), np.isnan(depth))


def test_the_tolerance_is_in_pixel_footprints():
    """A pixel whose neighbours leave the plane by 0.4 mm is filled when half a footprint is more (at 800 mm and f 500
    a footprint is 1.6 mm) and stays a hole when it is less."""
    depth = _slanted()
    depth[15, 15] = np.nan
    depth[14, 14] += 0.4
    _, loose = fill_pinholes(depth, CAMERA, None, 6, 0.5)
    _, tight = fill_pinholes(depth, CAMERA, None, 6, 0.1)
    assert loose[15, 15] and not tight[15, 15]


def test_neighbours_on_a_line_fill_nothing():
    """With 3 neighbours asked for, a pixel whose only neighbours with depth form a row has no plane."""
    depth = np.full((5, 5), np.nan, np.float32)
    depth[1, 1:4] = 800.0
    out, filled = fill_pinholes(depth, CAMERA, None, 3, 0.5)
    assert not filled[2, 2]
    assert np.isnan(out[2, 2])


def test_hole_fill_switches_the_stage_in_after_the_denoising():
    on = preset("tuned", hole_fill=6)
    stages = list(on.extraction.stages)
    assert stages[-1] == "hole_fill" and stages[-2] == "denoise"
    assert on.with_options(hole_fill=0).extraction.stages == preset("tuned").extraction.stages
    for name in ("fast", "accurate", "cpu-hashgrid"):  # the hash-grid presets close pinholes of 7 neighbours
        stages = [s for s in preset(name).extraction.stages if s != "edge_band"]  # fast's, accurate's last stage
        assert stages[-1] == "hole_fill" and preset(name).extraction.hole_fill == 7
    with pytest.raises(ConfigError, match="hole_fill"):
        preset("fast", hole_fill=9)


def test_extract_depth_with_the_hole_fill_marks_its_pixels(tiny_rods_field):
    """In the extraction (a tiny field on the small-rig rods), the filled pixels get the fate "interpolated" and a
    confidence; their count is in the timings; every other pixel is as without the stage."""
    from slwarp.neural.extraction import extract_depth, pixel_fates

    _, cfg, trainer = tiny_rods_field
    lit = trainer.renderer.valid_map.cpu().numpy()
    try:
        trainer.cfg = cfg
        plain = extract_depth(trainer, lit)
        trainer.cfg = cfg.with_options(hole_fill=5, hole_fill_footprints=2.0)
        got = extract_depth(trainer, lit)
    finally:
        trainer.cfg = cfg
    filled = got.fate == pixel_fates().index("interpolated")
    assert got.timings["hole_filled"] == int(filled.sum()) > 0
    assert np.isnan(plain.depth[filled]).all() and np.isfinite(got.depth[filled]).all()
    assert np.isfinite(got.confidence[filled]).all()
    np.testing.assert_array_equal(got.depth[~filled], plain.depth[~filled])
