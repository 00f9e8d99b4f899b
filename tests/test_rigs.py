"""The virtual scanner's built-in rigs: geometry as named, the same working volume lit on every rig."""
import numpy as np
import pytest

from slwarp.cli import main as cli_main
from slwarp.scans.scanner import Camera, Projector, look_at_rotation
from slwarp.sim.rigs import GEOMETRIES, RIG_NAMES, make_rig, parse_rig_name, rig_name
from slwarp.sim.scenes import SCENE_NAMES, build_scene
from slwarp.sim.simulate import SimOptions, render_geometry


def test_rig_names_cover_every_geometry_at_both_resolutions():
    assert set(GEOMETRIES) == {"default", "vertical", "oblique", "rolled"}
    assert len(RIG_NAMES) == 8 and len(set(RIG_NAMES)) == 8
    for g in GEOMETRIES:
        full, small = make_rig(rig_name(g)), make_rig(rig_name(g, small=True))
        assert (full[0].width, full[0].height, full[1].width, full[1].height) == (1280, 1024, 1280, 800)
        assert (small[0].width, small[0].height, small[1].width, small[1].height) == (320, 256, 640, 400)
        assert parse_rig_name(rig_name(g, True)) == (GEOMETRIES[g], True)
        # the small rig is the same geometry: same extrinsics, lenses scaled
        assert np.allclose(full[1].R, small[1].R) and np.allclose(full[1].T, small[1].T)
        for cam, proj in (full, small):  # lens distortion on both devices
            assert np.abs(cam.dist).max() > 0 and np.abs(proj.dist).max() > 0
    assert rig_name("default", True) == "small" and rig_name("rolled", True) == "small-rolled"
    with pytest.raises(ValueError, match="unknown rig 'tiny'.*small-oblique"):
        make_rig("tiny")


def test_default_and_small_rigs_unchanged():
    """The rigs of every earlier result, rebuilt here from their original numbers."""
    cam = Camera(1280, 1024, [[1800.0, 0, 641.3], [0, 1800.0, 509.6], [0, 0, 1]], [-0.06, 0.09, 2e-4, -3e-4, 0.0])
    c = np.array([150.0, 0.0, 0.0])
    R = look_at_rotation(c, np.array([0.0, 0.0, 750.0]))
    proj = Projector(1280, 800, [[1600.0, 0, 639.5], [0, 1600.0, 399.5], [0, 0, 1]], [0.03, -0.02, 0, 0, 0], R=R, T=-R @ c)
    for name, (ref_cam, ref_proj) in (("default", (cam, proj)), ("small", (cam.scaled(0.25), proj.scaled(0.5)))):
        got_cam, got_proj = make_rig(name)
        for a, b in ((got_cam, ref_cam), (got_proj, ref_proj)):
            assert (a.width, a.height) == (b.width, b.height)
            assert np.array_equal(a.K, b.K) and np.array_equal(a.dist, b.dist)
        assert np.array_equal(got_proj.R, ref_proj.R) and np.array_equal(got_proj.T, ref_proj.T)


EXPECTED_BASELINE = {  # unit direction camera -> projector, camera frame (x right, y down)
    "default": (1.0, 0.0, 0.0),
    "vertical": (0.0, 1.0, 0.0),
    "oblique": (np.sqrt(0.5), np.sqrt(0.5), 0.0),
    "rolled": (0.0, 1.0, 0.0),
}


@pytest.mark.parametrize("geometry", list(GEOMETRIES))
def test_baseline_direction_is_what_the_name_says(geometry):
    cam, proj = make_rig(geometry)
    direction = proj.center / np.linalg.norm(proj.center)
    assert np.allclose(direction, EXPECTED_BASELINE[geometry], atol=1e-9)
    # the projector looks at the working volume: its optical axis meets the camera's z axis at 750 mm
    axis = proj.R[2]
    t = -proj.center[0] / axis[0] if abs(axis[0]) > 1e-9 else -proj.center[1] / axis[1]
    assert np.allclose(proj.center + t * axis, [0.0, 0.0, 750.0], atol=1e-6)
    # which projector axis runs along the baseline: the camera centre in the projector frame is T; its
    # (x, y) part is the baseline as the projector's image plane sees it (x: columns, y: rows)
    angle = np.degrees(np.arctan2(abs(proj.T[1]), abs(proj.T[0])))
    expected_angle = {"default": 0.0, "rolled": 0.0, "vertical": 90.0, "oblique": 45.0}[geometry]
    assert angle == pytest.approx(expected_angle, abs=1.5)


def test_rolled_projector_columns_run_along_the_baseline_in_the_camera_image():
    """A step along a projector column (down the column, v increasing) moves across the camera image in x;
    a step along a projector row moves in camera y: the rolled projector's stripes are camera rows."""
    cam, proj = make_rig("rolled")
    X = np.array([0.0, 0.0, 750.0])
    uv = proj.project_camera_points(X)

    def camera_step(duv):
        d = proj.pixel_to_ray_in_camera(uv + duv)
        p = proj.center + d * ((X - proj.center)[2] / d[2])  # same depth as X
        return cam.project(p) - cam.project(X)

    step_u = camera_step(np.array([10.0, 0.0]))  # next column
    step_v = camera_step(np.array([0.0, 10.0]))  # next row
    assert abs(step_u[1]) > 10 * abs(step_u[0])  # columns advance down the camera image
    assert abs(step_v[0]) > 10 * abs(step_v[1])


@pytest.fixture(scope="module")
def scenes():
    return {s: build_scene(s) for s in SCENE_NAMES}


@pytest.mark.parametrize("geometry", list(GEOMETRIES))
def test_every_rig_lights_every_scene(scenes, geometry):
    """On the small rig of each geometry, most of the camera image is lit in every built-in scene (the default
    rig lights 74 to 81%), and most of the objects (points closer than 900 mm)."""
    cam, proj = make_rig(rig_name(geometry, small=True))
    for name, objects in scenes.items():
        geo = render_geometry(objects, cam, proj, SimOptions(), device="cpu")
        depth = geo.depth
        lit = geo.lit & np.isfinite(depth)
        near = np.isfinite(depth) & (depth < 900.0)
        assert np.isfinite(depth).mean() > 0.99, (geometry, name)  # the wall fills the view
        assert lit.mean() > 0.7, (geometry, name, lit.mean())
        assert near.sum() > 0.1 * depth.size and lit[near].mean() > 0.78, (geometry, name, lit[near].mean())
        d = depth[lit]
        assert 500.0 < d.min() and d.max() < 1100.0  # inside the shared depth range


def test_simulate_list_shows_every_rig(capsys):
    assert cli_main(["simulate", "--list"]) == 0
    out = capsys.readouterr().out
    for name in RIG_NAMES:
        assert name in out
