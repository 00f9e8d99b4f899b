"""A real capture's twin (slwarp.sim.twin): the plane and noise fits, the twin fitted to a hand-made capture of a
chessboard plate before a wall and a desk, and the twin rendered back through the simulator; the lens tail fitted
to every bit's edge profile at once (bench.edge_profile.fit_lens_tail); a twin's exact-depth metrics
(bench.real_captures.capture_metrics)."""
import dataclasses
import json

import numpy as np
import pytest

from slwarp.scans.scanner import Camera, Projector, camera_rays, look_at_rotation
from slwarp.sim.scenes import SceneObject
from slwarp.sim.simulate import CAMERA_MODELS, SimOptions
from slwarp.sim.twin import BOX_DEPTH_MM, PAPER_LIFT_MM, Twin, TwinBox, fit_noise, fit_plane, fit_twin


def unit(*v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


# --- fit_plane, fit_noise -------------------------------------------------------------------------------------------

def test_fit_plane_recovers_a_plane_among_outliers():
    rng = np.random.default_rng(0)
    n_true, d_true = unit(0.3, -0.2, 1.0), 700.0
    a = unit(*np.cross(n_true, [1.0, 0.0, 0.0]))
    b = np.cross(n_true, a)
    n_in, n_out = 1400, 600  # 30% outliers
    st = rng.uniform(-200.0, 200.0, (n_in, 2))
    on = n_true * d_true + st[:, :1] * a + st[:, 1:] * b + rng.normal(0.0, 0.5, (n_in, 1)) * n_true
    off = rng.uniform([-300.0, -300.0, 400.0], [300.0, 300.0, 1000.0], (n_out, 3))
    n, d, inl = fit_plane(np.concatenate([on, off]), inlier_mm=2.0)
    assert d > 0 and np.linalg.norm(n) == pytest.approx(1.0)
    assert np.degrees(np.arccos(min(n @ n_true, 1.0))) < 0.1
    assert d == pytest.approx(d_true, abs=0.2)
    assert inl.shape == (n_in + n_out,) and inl[:n_in].mean() > 0.99 and inl[n_in:].mean() < 0.03
    # a desk seen from above: its normal away from the camera (d > 0) points down, and a little toward it (n_z < 0)
    desk_n = unit(0.0, 1.0, -0.05)
    ahead = np.cross([1.0, 0.0, 0.0], desk_n)  # in the desk, away from the camera (+z)
    floor = desk_n * 115.0 + st[:, :1] * np.array([1.0, 0.0, 0.0]) + (st[:, 1:] + 800.0) * ahead
    n, d, _ = fit_plane(floor)
    assert n @ desk_n == pytest.approx(1.0, abs=1e-6) and d == pytest.approx(115.0, abs=1e-6)
    with pytest.raises(ValueError, match="3 points"):
        fit_plane(on[:2])


def _sense(rng, level, full_well, read_noise):
    """What the simulator's sensor does to a level [0, 1]: Poisson shot noise at full_well electrons plus Gaussian
    read noise (no quantisation)."""
    return rng.poisson(level * full_well) / full_well + rng.normal(0.0, read_noise, level.shape)


@pytest.mark.parametrize("black", ["flat", "ramp"])
def test_fit_noise_recovers_full_well_and_read_noise(black):
    """White, black and pattern + inverse pairs with shot noise at 3000 electrons and read noise 0.005: the fit
    finds both, and its per-level sigmas follow sqrt(level / full_well + read^2) (level: the mean of I, J, W and
    B). The black frame shot-noises like any level in the simulator (its black level is added before the noise),
    so a black frame that varies over the image (`ramp`) must not bend the fit."""
    rng = np.random.default_rng(3)
    fw, rd = 3000.0, 0.005
    H, W = 160, 240
    s = np.tile(np.linspace(0.05, 0.85, W), (H, 1))  # white - black: a ramp across the image
    b = np.full((H, W), 0.02) if black == "flat" else np.tile(np.linspace(0.0, 0.5, H)[:, None], (1, W))
    white, black_img = _sense(rng, s + b, fw, rd), _sense(rng, b, fw, rd)
    pairs = []
    for _ in range(4):
        p = (rng.random((H, W)) < 0.5).astype(np.float64)
        pairs.append((_sense(rng, s * p + b, fw, rd), _sense(rng, s * (1 - p) + b, fw, rd)))
    fit = fit_noise(pairs, white, black_img)
    assert fit["full_well"] == pytest.approx(fw, rel=0.07)  # within 4.3% over seeds 0-5; 10-15% off with the
    assert fit["read_noise"] == pytest.approx(rd, rel=0.15)  # ramp when the black frame's shot noise is missed
    assert len(fit["sigma_at"]) >= 8
    for level, sigma in fit["sigma_at"].items():
        assert sigma == pytest.approx(np.sqrt(float(level) / fw + rd ** 2), rel=0.08), level


# --- fit_twin on a hand-made capture --------------------------------------------------------------------------------

SQUARE_MM, SQUARES = 30.0, (6, 5)  # the print: 6 x 5 squares of 30 mm; the region is its inner 4 x 3
PLATE_CENTRE = np.array([10.0, -15.0, 600.0])
PLATE_N = unit(0.5, 0.0, np.sqrt(0.75))  # turned 30 deg about the camera's y, away from the camera on the right
PLATE_U, PLATE_V = unit(np.sqrt(0.75), 0.0, -0.5), np.array([0.0, 1.0, 0.0])  # v = n x u
WALL_N, WALL_POINT = unit(0.1, 0.0, 1.0), np.array([0.0, 0.0, 950.0])
# a desk 160 mm below at 900 mm, rising toward the camera: its normal away from the camera has n_z < 0
DESK_N, DESK_POINT = unit(0.0, 1.0, -0.05), np.array([0.0, 160.0, 900.0])
ALBEDO = {"plate": 0.35, "paper": 0.8, "white_squares": 0.75, "black_squares": 0.05, "wall": 0.6, "desk": 0.45}
R0, BLACK_LEVEL, FULL_WELL, READ_NOISE = 500.0, 0.02, 20000.0, 0.002  # the capture's radiometry (gain 1)
DEPTH_RANGE = (300.0, 1500.0)
PITCH_MM = PLATE_CENTRE[2] / 140.0  # the camera's pixel pitch on the plate


def small_rig():
    """A 96 x 80 camera (fx 140 px, mild distortion) and a 128 x 96 projector 100 mm above it, toed in to 600 mm."""
    camera = Camera(96, 80, [[140.0, 0.0, 47.5], [0.0, 140.0, 39.5], [0.0, 0.0, 1.0]], [-0.05, 0.02, 0.0, 0.0, 0.0])
    c = np.array([0.0, -100.0, 0.0])
    R = look_at_rotation(c, np.array([0.0, 0.0, 600.0]))
    projector = Projector(128, 96, [[80.0, 0.0, 63.5], [0.0, 80.0, 47.5], [0.0, 0.0, 1.0]], R=R, T=-R @ c)
    return camera, projector


def hand_capture(seed=0):
    """The capture fit_twin reads, computed by hand: every pixel's first hit on the plate (a 300 x 270 mm
    rectangle), the wall or the desk (planes); albedos by surface and by square; white = albedo x cos toward the
    projector x (R0 / distance)^2 + black level, black = the black level, both with the sensor's noise; three
    pattern + inverse pairs of projector column stripes; a depth map with 0.1 mm noise and no depth on the dark
    squares (no decoder gives one there), and the region between the print's outermost inner corners."""
    rng = np.random.default_rng(seed)
    camera, projector = small_rig()
    rays = camera_rays(camera)

    def hit(n, point):
        with np.errstate(divide="ignore"):
            t = (n @ point) / (rays @ n) * np.linalg.norm(rays, axis=-1)  # rays are unit: t is the distance
        return np.where(t > 0, t, np.inf)

    t_plate, t_wall, t_desk = hit(PLATE_N, PLATE_CENTRE), hit(WALL_N, WALL_POINT), hit(DESK_N, DESK_POINT)
    X_plate = rays * t_plate[..., None]
    s, t = (X_plate - PLATE_CENTRE) @ PLATE_U, (X_plate - PLATE_CENTRE) @ PLATE_V
    on_board = (np.abs(s) <= 150.0) & (np.abs(t) <= 135.0)
    t_plate = np.where(on_board, t_plate, np.inf)
    label = np.argmin(np.stack([t_plate, t_wall, t_desk]), 0)  # 0 plate, 1 wall, 2 desk
    assert np.isfinite(np.stack([t_plate, t_wall, t_desk]).min(0)).all()
    X = rays * np.stack([t_plate, t_wall, t_desk]).min(0)[..., None]
    normal = np.stack([PLATE_N, WALL_N, DESK_N])[label]
    albedo = np.array([0.0, ALBEDO["wall"], ALBEDO["desk"]])[label]
    plate = label == 0
    i, j = np.floor((s + 90.0) / SQUARE_MM).astype(int), np.floor((t + 75.0) / SQUARE_MM).astype(int)
    in_print = plate & (np.abs(s) <= 90.0) & (np.abs(t) <= 75.0)
    dark = in_print & ((i + j) % 2 == 0)  # the square at the plate's -u, -v corner is dark, as the twin's
    in_paper = plate & ~in_print & (np.abs(s) <= 120.0) & (np.abs(t) <= 105.0)
    albedo = np.where(plate, ALBEDO["plate"], albedo)
    albedo = np.where(in_paper, ALBEDO["paper"], albedo)
    albedo = np.where(in_print, np.where(dark, ALBEDO["black_squares"], ALBEDO["white_squares"]), albedo)
    to_p = projector.center - X
    dist = np.linalg.norm(to_p, axis=-1)
    cos = np.clip(-(to_p * normal).sum(-1) / dist, 0.0, 1.0)
    signal = albedo * cos * (R0 / dist) ** 2
    assert signal.max() < 0.95
    sense = lambda level: _sense(rng, level, FULL_WELL, READ_NOISE)  # noqa: E731
    black_true = np.full(signal.shape, BLACK_LEVEL)
    white, black = sense(signal + BLACK_LEVEL), sense(black_true)
    col = projector.project_camera_points(X)[..., 0]
    pairs = []
    for period in (6.0, 12.0, 24.0):
        p = (np.floor(np.nan_to_num(col) / period) % 2).astype(np.float64)
        pairs.append((sense(signal * p + BLACK_LEVEL), sense(signal * (1 - p) + BLACK_LEVEL)))
    depth = X[..., 2] + rng.normal(0.0, 0.1, X.shape[:2])
    depth[dark] = np.nan
    region = plate & (np.abs(s) <= 60.0) & (np.abs(t) <= 45.0)
    return {"camera": camera, "projector": projector, "depth": depth, "region": region, "white": white,
            "black": black, "pairs": pairs, "label": label, "true_depth": X[..., 2], "true_white": signal + BLACK_LEVEL}


@pytest.fixture(scope="module")
def fitted():
    cap = hand_capture()
    twin = fit_twin(cap["depth"], cap["region"], cap["white"], cap["black"], cap["pairs"], cap["camera"],
                    cap["projector"], DEPTH_RANGE, squares=SQUARES)
    return cap, twin


def test_fit_twin_finds_the_plate_its_print_and_the_wall_and_desk(fitted):
    cap, twin = fitted
    boxes = {b.name: b for b in twin.boxes}
    squares = [n for n in boxes if n.startswith("square_")]
    assert {"plate", "paper", "wall", "desk"} <= set(boxes) and len(boxes) == 4 + len(squares)
    assert sorted(squares) == sorted(f"square_{i}_{j}" for i in range(SQUARES[0]) for j in range(SQUARES[1]))
    # the plate: its plane (the depth noise is 0.1 mm), its centre and axes, its squares' size, its extents
    # (print + paper margin + plate margin: 10 x 9 squares). The region's extents come from pixel centres (4.3 mm
    # apart on the plate), so the sizes are a few percent short and its axes lean by 2 deg (0.13 deg at 4x the
    # resolution: the pixel grid, not the perspective).
    plate = boxes["plate"]
    n = np.asarray(plate.normal)
    assert np.degrees(np.arccos(min(n @ PLATE_N, 1.0))) < 0.2
    assert n @ np.asarray(plate.center) == pytest.approx(PLATE_N @ PLATE_CENTRE, abs=0.3)
    assert twin.report["plate_normal"] == pytest.approx(list(n))
    assert np.linalg.norm(np.asarray(plate.center) - PLATE_CENTRE) < 4.0
    assert np.asarray(plate.u) @ PLATE_U > 0.999 and np.asarray(plate.v) @ PLATE_V > 0.999
    assert twin.report["square_mm"] == pytest.approx(SQUARE_MM, rel=0.05)
    assert plate.extents == pytest.approx([10 * SQUARE_MM, 9 * SQUARE_MM], rel=0.05)
    assert boxes["paper"].extents == pytest.approx([8 * SQUARE_MM, 7 * SQUARE_MM], rel=0.05)
    # the paper and the squares stand in front of the plate (toward the camera), one lift each
    c = np.asarray(plate.center)
    assert np.asarray(boxes["paper"].center) - c == pytest.approx(-PAPER_LIFT_MM * n, abs=1e-9)
    sq00, sq10 = boxes["square_0_0"], boxes["square_1_0"]
    assert (np.asarray(sq00.center) - c) @ n == pytest.approx(-2 * PAPER_LIFT_MM, abs=1e-9)
    assert (np.asarray(sq00.center) - c) @ PLATE_U == pytest.approx(-2.5 * SQUARE_MM, abs=PITCH_MM)
    assert (np.asarray(sq00.center) - c) @ PLATE_V == pytest.approx(-2.0 * SQUARE_MM, abs=PITCH_MM)
    assert np.asarray(sq10.center) - np.asarray(sq00.center) == pytest.approx(sq10.extents[0] * np.asarray(plate.u))
    assert sq00.extents == pytest.approx([SQUARE_MM, SQUARE_MM], rel=0.06)
    # the wall and the desk: their planes
    for name, n_true, point in (("wall", WALL_N, WALL_POINT), ("desk", DESK_N, DESK_POINT)):
        b = boxes[name]
        assert np.asarray(b.normal) @ n_true > 0.9999, name  # away from the camera
        assert abs(np.asarray(b.normal) @ (np.asarray(b.center) - point)) < 0.5, name
    assert twin.report["wall_share"] > twin.report["desk_share"] > 0.02
    assert twin.report["wall_distance_mm"] == pytest.approx(np.median(cap["true_depth"][cap["label"] == 1]), rel=0.01)


def test_fit_twin_radiometry_is_the_simulators(fitted):
    """The albedos are the white frame minus the black one over the simulator's shading at the fitted ref_dist
    (gain 1): the hand capture's albedos times (R0 / ref_dist)^2; the dark squares are the even ones; the black
    level, the noise and the projector's focus on the board."""
    cap, twin = fitted
    rad = twin.radiometry
    assert rad["gain"] == 1.0 and rad["ambient"] == 0.0
    dist = np.linalg.norm(cap["projector"].center - PLATE_CENTRE)
    assert rad["ref_dist"] == pytest.approx(dist, rel=0.05)
    scale = (R0 / rad["ref_dist"]) ** 2
    assert set(twin.report["albedo"]) == set(ALBEDO)
    for name, a in twin.report["albedo"].items():
        # the dark squares' albedo is their 20% quantile (0.10 of the region): the noise pulls it down by ~0.8 sigma
        tol = 0.005 if name == "black_squares" else 0.003
        assert a == pytest.approx(ALBEDO[name] * scale, rel=0.02, abs=tol), name
    boxes = {b.name: b for b in twin.boxes}
    for i in range(SQUARES[0]):
        for j in range(SQUARES[1]):
            key = "black_squares" if (i + j) % 2 == 0 else "white_squares"
            assert boxes[f"square_{i}_{j}"].albedo == twin.report["albedo"][key]
    assert [boxes[k].albedo for k in ("plate", "paper", "wall", "desk")] == \
        [twin.report["albedo"][k] for k in ("plate", "paper", "wall", "desk")]
    assert rad["black_level"] == pytest.approx(BLACK_LEVEL, abs=5e-4)
    assert rad["full_well"] == pytest.approx(FULL_WELL, rel=0.2)
    assert 0.0 <= rad["read_noise"] < 0.004
    focus = (cap["projector"].R @ PLATE_CENTRE + cap["projector"].T)[2]
    assert rad["focus_dist"] == pytest.approx(focus, abs=3.0)
    assert twin.depth_range == DEPTH_RANGE


def test_twin_round_trips_through_json_and_gives_its_rig_scene_and_options(fitted):
    cap, twin = fitted
    back = Twin.from_dict(json.loads(json.dumps(twin.to_dict())))
    assert back == twin and isinstance(back.boxes[0], TwinBox) and isinstance(back.depth_range, tuple)
    camera, projector = back.rig()
    assert type(camera) is Camera and isinstance(projector, Projector)
    assert np.array_equal(camera.K, cap["camera"].K) and np.array_equal(camera.dist, cap["camera"].dist)
    assert (camera.width, camera.height, projector.width, projector.height) == (96, 80, 128, 96)
    assert np.allclose(projector.R, cap["projector"].R) and np.allclose(projector.T, cap["projector"].T)
    assert np.array_equal(projector.K, cap["projector"].K)
    objects = back.scene_objects()
    assert [o.name for o in objects] == [b.name for b in twin.boxes]
    assert all(isinstance(o, SceneObject) for o in objects)
    for o, b in zip(objects, twin.boxes):
        assert o.albedo == pytest.approx(b.albedo)
        # the box's front face lies on its plane, the box behind it (away from the camera)
        n, c = np.asarray(b.normal), np.asarray(b.center)
        rel = np.asarray(o.mesh.vertices) - c
        h = rel @ n
        assert h.min() == pytest.approx(0.0, abs=1e-6) and h.max() == pytest.approx(BOX_DEPTH_MM, abs=1e-6), b.name
        uv = np.stack([rel @ np.asarray(b.u), rel @ np.asarray(b.v)], 1)
        assert np.abs(uv).max(0) == pytest.approx(np.asarray(b.extents) / 2), b.name
        # flat faces: the simulator shades with the vertex normals interpolated, which must be the faces' own
        assert np.allclose(o.mesh.vertex_normals[o.mesh.faces], o.mesh.face_normals[:, None, :]), b.name
    opts = back.sim_options("procam", seed=4)
    assert isinstance(opts, SimOptions) and opts.seed == 4
    for k, v in twin.radiometry.items():
        assert getattr(opts, k) == v, k
    assert opts.black_level == twin.radiometry["black_level"] != CAMERA_MODELS["procam"]["black_level"]
    for k in ("near_halo", "near_halo_sigma", "halo", "halo_sigma", "supersample", "defocus_slope"):
        assert getattr(opts, k) == CAMERA_MODELS["procam"][k], k
    assert back.sim_options("linear").halo == 0.0 and back.sim_options("linear").ref_dist == twin.radiometry["ref_dist"]


def test_the_twin_rendered_gives_back_the_capture(fitted, device):
    """The twin's boxes through the simulator (noise, defocus and quantisation off, its radiometry): the exact
    depth is the capture's surfaces (the print 0.4 mm in front), the white frame the capture's without its noise
    (the boxes' faces shaded by their plane's normal), the black frame the black level."""
    from slwarp.scans.patterns import named_set
    from slwarp.sim.simulate import simulate

    cap, twin = fitted
    camera, projector = twin.rig()
    opts = dataclasses.replace(twin.sim_options("linear"), noise=False, defocus=False, bits=0)
    scan = simulate(twin.scene_objects(), camera, projector, named_set("whiteblack", projector.width, projector.height),
                    opts, depth_range=twin.depth_range, device=device)
    from scipy.ndimage import binary_erosion

    # each surface but its outermost 2 pixels: the fitted plate's edges lie within a pixel pitch of the true ones
    label, lit = cap["label"], scan.mask
    inner = [binary_erosion(label == k, iterations=2) for k in range(3)]  # plate, wall, desk
    assert lit.mean() > 0.9 and all(m.sum() > 500 for m in inner)
    dz = np.abs(scan.gt_depth - cap["true_depth"])
    for k, tol in ((0, 0.6), (1, 0.3), (2, 0.3)):  # the print 0.4 mm in front, the paper 0.2 mm; 0.1 mm depth noise
        assert np.quantile(dz[inner[k]], 0.95) < tol, k
    dw = np.abs(scan.image("white") - cap["true_white"])
    for k in (1, 2):  # uniform planes: the fitted albedo's error alone (<= 2%)
        assert np.quantile(dw[lit & inner[k]], 0.95) < 0.01, k
    plate = lit & inner[0]
    assert np.median(dw[plate]) < 0.01 and (dw[plate] < 0.03).mean() > 0.85  # the squares' edges fall a bit off
    assert np.abs(scan.image("black")[lit] - twin.radiometry["black_level"]).max() < 1e-6


# --- the lens's tail, fitted to every bit's edge profile at once ----------------------------------------------------

def _blurred_stripes(d, spacing, core, halos, step=0.05, reach=3000.0):
    """Stripes of width `spacing` projector px (white on (0, spacing), dark on (-spacing, 0), periodic), sampled
    every `step` px and convolved with the lens (a Gaussian core and Gaussian halos, [(share, sigma)]), read at
    the distances `d` to the edge at 0."""
    from scipy.signal import fftconvolve

    x = (np.arange(-round(reach / step), round(reach / step)) + 0.5) * step  # the edges fall between samples
    pattern = (np.floor(x / spacing) % 2 == 0).astype(np.float64)
    k = np.arange(-int(6 * 60 / step), int(6 * 60 / step) + 1) * step
    gauss = lambda s: np.exp(-0.5 * (k / s) ** 2) / np.exp(-0.5 * (k / s) ** 2).sum()  # noqa: E731
    psf = (1 - sum(h for h, _ in halos)) * gauss(core) + sum(h * gauss(s) for h, s in halos)
    return np.interp(d, x, fftconvolve(pattern, psf, mode="same"))


def test_fit_lens_tail_recovers_a_core_and_two_halos():
    from bench.edge_profile import fit_lens_tail

    core, halos = 0.6, [(0.15, 3.0), (0.085, 49.0)]
    profiles = []
    for spacing, lo, hi in ((256.0, 0.03, 0.95), (128.0, 0.02, 0.97), (32.0, 0.05, 0.9), (16.0, 0.04, 0.93)):
        d = np.arange(-59.5, 60.0, 1.0)  # bench.edge_profile's bins: +-60 px, 1 px
        x = lo + (hi - lo) * _blurred_stripes(d, spacing, core, halos)
        x[np.abs(d) > spacing / 2] = np.nan  # a profile reaches half way to the next edge, NaN beyond
        profiles.append({"d": d.tolist(), "x": x.tolist(), "edge_spacing_px": spacing})
    fit = fit_lens_tail(profiles)
    assert fit["core_px"] == pytest.approx(core, abs=0.05)
    (near_share, near_sigma), (far_share, far_sigma) = fit["halos"]
    assert near_sigma < far_sigma
    assert near_share == pytest.approx(0.15, abs=0.015) and near_sigma == pytest.approx(3.0, rel=0.1)
    assert far_share == pytest.approx(0.085, abs=0.01) and far_sigma == pytest.approx(49.0, rel=0.1)
    assert fit["rms"] < 1e-4
    # one scale cannot fit both halos
    assert fit_lens_tail(profiles, scales=1)["rms"] > 5 * fit["rms"]


# --- a twin's exact depth in bench.real_captures --------------------------------------------------------------------

def test_capture_metrics_measure_a_twins_exact_depth():
    from bench import real_captures

    camera = Camera(5, 4, [[10.0, 0.0, 2.0], [0.0, 10.0, 1.5], [0.0, 0.0, 1.0]])
    gt = np.full((4, 5), 500.0)
    gt[0, 0] = np.nan  # no surface there
    mask = np.ones((4, 5), bool)
    mask[3, 4] = False  # not lit: not judged
    depth = gt + np.arange(20.0).reshape(4, 5) * 0.1  # errors 0.0, 0.1, ..., 1.9 mm
    depth[1, 1] = np.nan  # a hole
    region = np.zeros((4, 5), bool)
    region[1:3, 1:4] = True
    ref = {"region": region, "full_decode": gt.copy()}
    plain = real_captures.capture_metrics(depth, ref, camera)
    assert not any(k.startswith("gt_") for k in plain)
    m = real_captures.capture_metrics(depth, {**ref, "gt_depth": gt, "gt_mask": mask}, camera)
    judged = np.isfinite(gt) & mask  # 18 pixels, 17 with a depth
    both = judged & np.isfinite(depth)
    err = np.abs(depth - gt)[both]
    assert both.sum() == 17 and judged.sum() == 18
    assert m["gt_mae_mm"] == pytest.approx(err.mean()) and m["gt_mae_mm"] == pytest.approx(
        (sum(range(1, 19)) - 6) * 0.1 / 17)
    assert m["gt_rmse_mm"] == pytest.approx(np.sqrt((err ** 2).mean()))
    assert m["gt_completeness"] == pytest.approx(17 / 18)
    assert {k: v for k, v in m.items() if not k.startswith("gt_")} == pytest.approx(plain, nan_ok=True)
