"""Scanner geometry: round trips, and agreement with OpenCV's projectPoints / undistortPoints."""
import cv2
import numpy as np
import pytest
import torch

from slwarp.sim.rigs import make_rig
from slwarp.scans.scanner import CalibrationError, Camera, Projector, check_rotation, look_at_rotation


def random_camera(rng, strength=1.0):
    K = np.array([[rng.uniform(800, 2000), 0, rng.uniform(600, 680)], [0, rng.uniform(800, 2000), rng.uniform(480, 540)], [0, 0, 1]])
    dist = np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), rng.uniform(-2e-3, 2e-3), rng.uniform(-2e-3, 2e-3), rng.uniform(-0.2, 0.2)]) * strength
    return Camera(1280, 1024, K, dist)


def random_points_in_view(cam, rng, n=500):
    uv = np.stack([rng.uniform(0, cam.width - 1, n), rng.uniform(0, cam.height - 1, n)], -1)
    z = rng.uniform(300, 2000, n)
    d = cam.pixel_to_ray(uv)
    return uv, d / d[:, 2:3] * z[:, None]


@pytest.mark.parametrize("seed", range(5))
def test_project_matches_opencv(seed):
    rng = np.random.default_rng(seed)
    cam = random_camera(rng)
    _, X = random_points_in_view(cam, rng)
    ours = cam.project(X)
    ref, _ = cv2.projectPoints(X.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.K, cam.dist)
    assert np.abs(ours - ref.reshape(-1, 2)).max() < 1e-3


@pytest.mark.parametrize("seed", range(5))
def test_undistort_matches_opencv(seed):
    rng = np.random.default_rng(100 + seed)
    cam = random_camera(rng)
    uv = np.stack([rng.uniform(0, cam.width - 1, 500), rng.uniform(0, cam.height - 1, 500)], -1)
    ours = cam.pixel_to_normalized(uv)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)
    ref = cv2.undistortPoints(uv.reshape(-1, 1, 2), cam.K, cam.dist, None, None, None, crit).reshape(-1, 2)
    # compare in pixels of an ideal camera with the same focal length
    err_px = np.abs(ours - ref) * np.array([cam.fx, cam.fy])
    assert err_px.max() < 1e-3


@pytest.mark.parametrize("seed", range(3))
def test_round_trip_pixel_ray_pixel(seed):
    rng = np.random.default_rng(200 + seed)
    cam = random_camera(rng)
    uv, X = random_points_in_view(cam, rng)
    assert np.abs(cam.project(X) - uv).max() < 1e-6
    d = cam.pixel_to_ray(uv)
    assert np.allclose(np.linalg.norm(d, axis=-1), 1.0)


def test_torch_matches_numpy_any_dtype():
    rng = np.random.default_rng(3)
    cam = random_camera(rng)
    uv, X = random_points_in_view(cam, rng, 100)
    for dtype in (torch.float64, torch.float32):
        Xt = torch.as_tensor(X, dtype=dtype)
        out = cam.project(Xt)
        assert isinstance(out, torch.Tensor) and out.dtype == dtype
        tol = 1e-6 if dtype == torch.float64 else 5e-3
        assert np.abs(out.numpy() - cam.project(X)).max() < tol
        d = cam.pixel_to_ray(torch.as_tensor(uv, dtype=dtype))
        assert np.abs(d.numpy() - cam.pixel_to_ray(uv)).max() < (1e-9 if dtype == torch.float64 else 1e-5)


def test_torch_on_cuda(device):
    cam = make_rig("default")[0]
    uv = torch.tensor([[10.0, 20.0], [640.0, 512.0]], device=device, dtype=torch.float64)
    d = cam.pixel_to_ray(uv)
    assert d.device == uv.device
    assert torch.allclose(cam.project(d * 700.0), uv, atol=1e-6)


def test_projector_round_trip_and_frames():
    cam, proj = make_rig("default")
    rng = np.random.default_rng(5)
    uvp = np.stack([rng.uniform(0, proj.width - 1, 200), rng.uniform(0, proj.height - 1, 200)], -1)
    dcam = proj.pixel_to_ray_in_camera(uvp)
    X = proj.center + dcam * rng.uniform(400, 1200, (200, 1))
    assert np.abs(proj.project_camera_points(X) - uvp).max() < 1e-6
    # X_p = R X_c + T: the projector centre maps to the origin
    assert np.allclose(proj.camera_to_projector(proj.center[None])[0], 0.0, atol=1e-9)
    ref, _ = cv2.projectPoints(X.reshape(-1, 1, 3), cv2.Rodrigues(proj.R)[0], proj.T, proj.K, proj.dist)
    assert np.abs(ref.reshape(-1, 2) - uvp).max() < 1e-3


def test_points_behind_or_far_outside_are_nan():
    cam = Camera(640, 480, [[500, 0, 320], [0, 500, 240], [0, 0, 1]], [0.1, -0.4, 0, 0, 2.0])
    out = cam.project(np.array([[0, 0, -100.0], [5000.0, 0, 100.0], [1.0, 1.0, 100.0]]))
    assert np.isnan(out[0]).all() and np.isnan(out[1]).all() and np.isfinite(out[2]).all()


def test_scaled_camera_keeps_pixel_centres():
    cam = make_rig("default")[0]
    small = cam.scaled(0.25)
    X = np.array([[30.0, -20.0, 700.0]])
    # a point's pixel scales about the image corner (-0.5, -0.5)
    assert np.allclose((cam.project(X) + 0.5) * 0.25 - 0.5, small.project(X), atol=1e-9)


@pytest.mark.parametrize(
    "K, message",
    [
        ([[np.nan, 0, 1], [0, 1, 1], [0, 0, 1]], "non-finite"),
        ([[0.0, 0, 1], [0, 1, 1], [0, 0, 1]], "singular"),
        ([[1.0, 0, 1], [0, 1, 1], [0, 1, 1]], "singular"),
    ],
)
def test_bad_intrinsics_raise(K, message):
    with pytest.raises(CalibrationError, match=message):
        Camera(10, 10, K)


def test_rotation_checks():
    R = look_at_rotation(np.array([100.0, 0, 0]), np.array([0, 0, 700.0]))
    assert np.allclose(check_rotation(R) @ R.T, np.eye(3))
    with pytest.raises(CalibrationError, match="not a rotation"):
        check_rotation(R * 1.01)
    with pytest.raises(CalibrationError, match="not a rotation"):
        check_rotation(np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(CalibrationError, match="not a rotation"):
        Projector(10, 10, np.eye(3), R=np.diag([1.0, 1.0, -1.0]))


def test_packed_projector_names_its_floats():
    _, proj = make_rig("small")
    rng = np.random.default_rng(4)
    proj = Projector(proj.width, proj.height, proj.K, [0.05, -0.02, 0.001, -0.002, 0.01], R=proj.R, T=[150.0, -3.0, 2.0])
    p = proj.packed
    assert len(p) == 24 and all(type(x) is float for x in p)
    assert p.R == tuple(proj.R.ravel()) and p.T == (150.0, -3.0, 2.0)
    assert (p.fx, p.fy, p.cx, p.cy) == (proj.fx, proj.fy, proj.cx, proj.cy)
    assert (p.k1, p.k2, p.p1, p.p2, p.k3) == (0.05, -0.02, 0.001, -0.002, 0.01) and p.dist == tuple(proj.dist)
    assert (p.width, p.height, p.max_r2) == (proj.width, proj.height, proj.max_normalized_r2)
    # the torch twin's projection reads the packed floats and agrees with the projector's own model
    from slwarp.neural.ops import twin

    uvp = np.stack([rng.uniform(0, proj.width - 1, 200), rng.uniform(0, proj.height - 1, 200)], -1)
    X = torch.as_tensor(proj.center + proj.pixel_to_ray_in_camera(uvp) * rng.uniform(400, 1200, (200, 1)))
    uv, ok = twin.project_to_projector(X, p)
    assert ok.all()
    np.testing.assert_allclose(uv.numpy(), proj.project_camera_points(X.numpy()), rtol=0, atol=1e-9)
