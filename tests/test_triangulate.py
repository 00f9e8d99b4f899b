"""Triangulation: exact correspondences (projections of known surfaces through both distorted lenses)
give the known depth back to 0.01 mm by the column plane, the row plane and the ray-ray midpoint."""
import numpy as np
import pytest

from slwarp.decode import choose_plane_axis, reconstruct_depth, triangulate, triangulate_midpoint, triangulate_plane
from slwarp.evaluation.outputs import write_points_ply as write_ply
from slwarp.sim.rigs import make_rig
from slwarp.scans.scanner import Camera, Projector


def real_like_rig():
    """The calibration of the real capture (strong distortion, mostly vertical baseline, principal point
    of the projector near its bottom edge), copied here so the test does not need the data."""
    cam = Camera(1280, 1024, [[3452.39, 0, 587.173], [0, 3449.92, 521.446], [0, 0, 1]],
                 [-0.222263, -0.866432, -7.27888e-4, -1.68841e-3, 3.13253])
    R = np.array([[0.999073, 0.0145577, -0.0405153], [-0.0120663, 0.998060, 0.0610733], [0.0413258, -0.0605278, 0.997311]])
    U, _, Vt = np.linalg.svd(R)  # the printed digits are not exactly orthonormal
    proj = Projector(1024, 768, [[1947.16, 0, 448.864], [0, 1933.99, 719.975], [0, 0, 1]],
                     [-0.0912255, 1.14485, -2.26955e-3, -9.31229e-3, -7.79792], R=U @ Vt, T=[39.0631, -278.264, -61.9474])
    return cam, proj


def surface_depth(cam, z0, amp):
    """A smooth non-planar depth map [H, W] (mm): a tilted plane with a bump."""
    uv = cam.pixel_grid()
    x, y = uv[..., 0] / cam.width - 0.5, uv[..., 1] / cam.height - 0.5
    return z0 * (1 + 0.15 * x - 0.1 * y) + amp * np.exp(-(x**2 + y**2) / 0.05)


def correspondences(cam, proj, depth):
    d = cam.pixel_to_ray(cam.pixel_grid())
    X = d * (depth / d[..., 2])[..., None]
    uv = proj.project_camera_points(X)
    inside = proj.in_image(uv) & np.isfinite(uv).all(-1)
    uv[~inside] = np.nan
    return uv, X


@pytest.mark.parametrize("rig", ["default", "small", "real"])
def test_exact_correspondences_give_exact_depth(rig):
    cam, proj = real_like_rig() if rig == "real" else make_rig(rig)
    cam = cam.scaled(0.25) if cam.width > 400 else cam  # the same lens on fewer pixels: a fast test
    depth = surface_depth(cam, 1600.0 if rig == "real" else 750.0, -60.0)
    uv, X = correspondences(cam, proj, depth)
    ok = np.isfinite(uv).all(-1)
    assert ok.mean() > 0.5
    for mode in ("col", "row", "midpoint"):
        z, pts, info = triangulate(cam, proj, uv[..., 0], uv[..., 1], mode)
        assert info["mode"] == mode
        assert np.isfinite(z[ok]).all() and np.isnan(z[~ok]).all()
        # both planes are exact in theory; the one across the baseline is ill-conditioned (its rays nearly
        # contain the camera ray), so only the one along the baseline is held to 0.01 mm on every pixel
        if mode == "midpoint" or mode == choose_plane_axis(proj):
            assert np.abs(z - depth)[ok].max() < 0.01
            assert np.abs(pts - X)[ok].max() < 0.01
    assert choose_plane_axis(proj) == ("row" if rig == "real" else "col")


def test_plane_iteration_handles_projector_distortion():
    """The column surface of a distorted projector is curved: the plane of the column's ray at the
    principal row alone is off by a visible amount; the refined solution is exact, and a solution that
    does not reproject onto its column is rejected (NaN)."""
    from slwarp.decode.triangulate import _plane_intersection

    cam, proj = make_rig("default")
    cam = cam.scaled(0.25)
    depth = surface_depth(cam, 750.0, 0.0)
    uv, _ = correspondences(cam, proj, depth)
    ok = np.isfinite(uv[..., 0])
    d = cam.pixel_to_ray(cam.pixel_grid())[ok]
    xn = proj.pixel_to_normalized(np.stack([uv[..., 0][ok], np.full(ok.sum(), proj.cy)], -1))[:, 0]
    naive = (d * _plane_intersection(d, proj, xn, "col")[:, None])[:, 2]
    assert np.abs(naive - depth[ok]).max() > 0.1
    full = triangulate_plane(cam, proj, uv[..., 0], "col")
    assert np.abs(full[..., 2] - depth)[ok].max() < 1e-6
    unrefined = triangulate_plane(cam, proj, uv[..., 0], "col", iterations=0)[..., 2][ok]
    off = np.abs(naive - depth[ok]) > 0.1  # the naive plane is wrong there by far more than the tolerance
    assert np.isnan(unrefined[off]).all()


def test_simulated_scan_correspondences(device):
    """GT depth of a simulated scan -> its projector coordinates -> triangulation gives the GT back."""
    from slwarp.sim.simulate import simulate_scene

    scan = simulate_scene("steps", "whiteblack", "small", device=device)
    uv, _ = correspondences(scan.camera, scan.projector, scan.gt_depth.astype(np.float64))
    z, _, info = triangulate(scan.camera, scan.projector, uv[..., 0], None)
    assert info["mode"] == "col"
    ok = scan.mask
    assert ok.mean() > 0.5 and np.abs(z - scan.gt_depth)[ok].max() < 0.01


def test_midpoint_gap_and_invalid_inputs():
    cam, proj = make_rig("small")
    depth = surface_depth(cam, 700.0, 30.0)
    uv, _ = correspondences(cam, proj, depth)
    pts, gap = triangulate_midpoint(cam, proj, uv[..., 0], uv[..., 1])
    ok = np.isfinite(uv).all(-1)
    assert np.nanmax(gap[ok]) < 1e-6
    # a row off by 5 px: the rays miss each other by millimetres
    _, gap5 = triangulate_midpoint(cam, proj, uv[..., 0], uv[..., 1] + 5)
    assert np.nanmin(gap5[ok]) > 0.5
    # NaN coordinates stay NaN; no coordinate at all is an error; midpoint needs both
    col = uv[..., 0].copy()
    col[:10] = np.nan
    z, _, _ = triangulate(cam, proj, col, None)
    assert np.isnan(z[:10]).all()
    with pytest.raises(ValueError, match="needs a decoded projector column or row"):
        triangulate(cam, proj, None, None)
    with pytest.raises(ValueError, match="midpoint triangulation needs both"):
        triangulate(cam, proj, col, None, "midpoint")


def test_depth_range_and_points_behind_camera():
    cam, proj = make_rig("small")
    depth = surface_depth(cam, 700.0, 0.0)
    uv, _ = correspondences(cam, proj, depth)
    z, pts, _ = triangulate(cam, proj, uv[..., 0], None, depth_range=(650.0, 720.0))
    fin = np.isfinite(z)
    assert fin.any() and (z[fin] >= 650).all() and (z[fin] <= 720).all()
    assert np.array_equal(np.isfinite(pts).all(-1), fin)
    # columns left of where the camera rays can meet them triangulate behind the camera: NaN, not negative
    z, _, _ = triangulate(cam, proj, np.full(depth.shape, -0.5), None)
    assert not (z[np.isfinite(z)] <= 0).any()


def test_row_plane_chosen_for_vertical_baseline():
    cam, proj = make_rig("small")
    vertical = Projector(proj.width, proj.height, proj.K, proj.dist, R=np.eye(3), T=[10.0, -150.0, 0.0])
    assert choose_plane_axis(vertical) == "row" and choose_plane_axis(proj) == "col"


def test_write_ply(tmp_path):
    pts = np.array([[[0, 0, 500], [np.nan, 0, 0]], [[1, 2, 3], [4, 5, 6]]], float)
    n = write_ply(tmp_path / "a.ply", pts, np.array([[0.0, 1.0], [0.5, 1.0]]))
    assert n == 3
    data = (tmp_path / "a.ply").read_bytes()
    head, body = data.split(b"end_header\n")
    assert b"element vertex 3" in head and b"property uchar red" in head
    rec = np.frombuffer(body, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1"),
                                     ("a", "u1")])  # trimesh writes RGBA
    assert rec["z"].tolist() == [500, 3, 6] and rec["r"].tolist() == [0, 128, 255]
    assert write_ply(tmp_path / "b.ply", pts) == 3


def test_reconstruct_depth_uses_scan_depth_range(device):
    from slwarp.sim.simulate import SimOptions, simulate_scene

    scan = simulate_scene("spheres", "gray7inv", "small", SimOptions(noise=False, defocus=False, bits=0), device=device)
    depth, points, dec = reconstruct_depth(scan, "gc-interp")
    fin = np.isfinite(depth)
    near, far = scan.depth_range
    assert (depth[fin] >= near).all() and (depth[fin] <= far).all()
    assert dec.extra["triangulation"] == "col" and points.shape == depth.shape + (3,)
    # 5 px stripes of a 640 px projector at 600 to 950 mm: ~0.15 px of interpolation error is ~1 mm
    assert np.nanmedian(np.abs(depth - scan.gt_depth)[scan.mask]) < 2.0
