"""The edge band at extraction (slwarp.neural.extraction.surface.edge_band_masks and its stage, edge_band): the
depths within a few pixels of a depth edge of the field stay only where the codes fit them well."""
import numpy as np
import pytest

from slwarp.neural.config import ConfigError, preset
from slwarp.neural.extraction.surface import edge_band_masks
from slwarp.scans.scanner import Camera

CAMERA = Camera(width=40, height=30, K=np.array([[500.0, 0, 19.5], [0, 500.0, 14.5], [0, 0, 1]]))


def edge_band_pixels(depth, camera, radius, footprints, sides):
    """The band as the stage draws it with one radius: behind the edges, and in front of them too with sides "both"."""
    near, far = edge_band_masks(depth, camera, radius if sides == "both" else 0, radius, footprints)
    return near | far


def _disc_before_a_wall(H=30, W=40):
    """[H, W] float32 mm: a wall at 800 mm and, in front of it, a square at 500 mm over rows 10-19, columns 15-24."""
    depth = np.full((H, W), 800.0, np.float32)
    depth[10:20, 15:25] = 500.0
    return depth


def test_the_far_side_is_the_wall_within_the_radius_of_the_square():
    depth = _disc_before_a_wall()
    far = edge_band_pixels(depth, CAMERA, 2, 10.0, "far")
    square = depth < 600
    expected = np.zeros_like(square)
    expected[8:22, 13:27] = True  # the square grown by 2 pixels (a 5 x 5 window's reach)
    expected &= ~square
    np.testing.assert_array_equal(far, expected)


def test_both_sides_add_the_squares_own_rim():
    depth = _disc_before_a_wall()
    both = edge_band_pixels(depth, CAMERA, 2, 10.0, "both")
    far = edge_band_pixels(depth, CAMERA, 2, 10.0, "far")
    rim = np.zeros(depth.shape, bool)
    rim[10:20, 15:25] = True
    rim[12:18, 17:23] = False  # the square's pixels more than 2 pixels inside its edge
    np.testing.assert_array_equal(both, far | rim)


def test_no_edge_no_band_and_nan_makes_no_edge():
    v, u = np.mgrid[0:30, 0:40].astype(np.float32)
    slanted = 800.0 + 2.0 * u + 1.0 * v  # 2 mm a pixel: under the 16 mm of 10 footprints at 800 mm
    assert not edge_band_pixels(slanted, CAMERA, 3, 10.0, "both").any()
    holed = slanted.copy()
    holed[5:9, 5:9] = np.nan
    band = edge_band_pixels(holed, CAMERA, 3, 10.0, "both")
    assert not band.any()  # a hole is no edge, and its pixels are never in the band
    assert not edge_band_pixels(_disc_before_a_wall(), CAMERA, 0, 10.0, "both").any()


def test_the_jump_is_in_pixel_footprints():
    """A 20 mm step at 800 mm is 12.5 footprints (f 500): an edge at 10 footprints, none at 15."""
    depth = np.full((30, 40), 800.0, np.float32)
    depth[:, 20:] = 820.0
    assert edge_band_pixels(depth, CAMERA, 1, 10.0, "both")[:, 19:21].all()
    assert not edge_band_pixels(depth, CAMERA, 1, 15.0, "both").any()


def test_edge_band_switches_the_stage_in_last():
    on = preset("tuned", edge_band_radius=2)
    assert list(on.extraction.stages)[-1] == "edge_band" and on.extraction.edge_band_sides == "both"
    assert on.with_options(edge_band_radius=0).extraction.stages == preset("tuned").extraction.stages
    for name in ("fast", "accurate"):  # the GPU hash-grid presets: 3 pixels, both sides, confidence 0.8
        ex = preset(name).extraction
        assert ex.stages[-1] == "edge_band" and ex.stages[-2] == "hole_fill"
        assert (ex.edge_band_radius, ex.edge_band_sides, ex.edge_band_confidence) == (3, "both", 0.8)
        assert ex.edge_readmit
    with pytest.raises(ConfigError, match="edge_band_sides"):
        preset("fast", edge_band_sides="near")


def test_the_stage_drops_exactly_the_weak_depths_in_the_band():
    """Run by the extraction's runner on a square before a wall: the depths in the band (3 pixels, both sides) whose
    confidence is under the bar lose their depth with the fate "edge_band", counted in the timings; the band's
    confident depths and every depth outside it stay; without the flying-pixel filter's edge_filter it does nothing."""
    from types import SimpleNamespace

    from slwarp.neural.extraction.runner import build_stages, run_stages
    from slwarp.neural.extraction.state import State, pixel_fates

    field = _disc_before_a_wall()
    depth = field.copy()
    depth[0, 0] = np.nan  # a pixel without depth stays so
    rng = np.random.default_rng(0)
    confidence = rng.uniform(0.6, 1.0, field.shape).astype(np.float32)
    confidence[0, 0] = np.nan
    inputs = SimpleNamespace(camera=CAMERA, device="cpu", valid=None)
    state = State.start(inputs, None).replace(depth=depth, confidence=confidence, field_depth=field)
    ex = preset("tuned", edge_band_radius=3, edge_band_confidence=0.8).extraction
    [stage] = [s for s in build_stages(ex) if s.name == "edge_band"]
    after = run_stages([stage], state, score=None)  # it only drops: nothing to score
    band = edge_band_pixels(field, CAMERA, 3, 10.0, "both")
    weak = band & (confidence < 0.8)
    assert weak.sum() > 20 and (band & (confidence >= 0.8)).sum() > 20
    np.testing.assert_array_equal(np.isnan(after.depth), weak | np.isnan(depth))
    np.testing.assert_array_equal(after.fate == pixel_fates().index("edge_band"), weak)
    assert after.timings["edge_band_dropped"] == after.timings["dropped"]["edge_band"] == int(weak.sum())
    assert np.isnan(after.confidence[weak]).all()
    off = build_stages(preset("tuned", edge_band_radius=3, edge_readmit=False, edge_filter=0).extraction)[-1]
    assert off.name == "edge_band" and run_stages([off], state, score=None).depth is depth


def test_the_far_side_takes_its_own_width_and_bar():
    """edge_band_masks gives the square's rim (in front) and the wall around it (behind) each with its own radius;
    the stage holds the wall's band to edge_band_far_confidence over edge_band_far_radius pixels, the rim to the
    common bar."""
    from types import SimpleNamespace

    from slwarp.neural.extraction.runner import build_stages, run_stages
    from slwarp.neural.extraction.state import State
    field = _disc_before_a_wall()
    near, far = edge_band_masks(field, CAMERA, 2, 4, 10.0)
    np.testing.assert_array_equal(near | edge_band_pixels(field, CAMERA, 2, 10.0, "far"),
                                  edge_band_pixels(field, CAMERA, 2, 10.0, "both"))
    wide = np.zeros(field.shape, bool)
    wide[6:24, 11:29] = True  # the square grown by 4 pixels
    np.testing.assert_array_equal(far, wide & (field > 600))
    assert not edge_band_masks(field, CAMERA, 0, 0, 10.0)[0].any()

    confidence = np.full(field.shape, 0.85, np.float32)  # over the common bar, under the far one
    inputs = SimpleNamespace(camera=CAMERA, device="cpu", valid=None)
    state = State.start(inputs, None).replace(depth=field.copy(), confidence=confidence, field_depth=field)
    ex = preset("tuned", edge_band_radius=2, edge_band_far_radius=4, edge_band_far_confidence=0.9).extraction
    stage = build_stages(ex)[-1]
    after = run_stages([stage], state, score=None)
    np.testing.assert_array_equal(np.isnan(after.depth), far)  # the wall's 4-pixel band; the rim passes 0.8
    same = build_stages(preset("tuned", edge_band_radius=2).extraction)[-1]
    assert run_stages([same], state, score=None).depth is state.depth  # 0.85 passes both bars of 0.8
