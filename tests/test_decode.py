"""Classical decoders: code tables from pattern images, exactness on noise-free simulated planes, NaN (never
garbage) under noise, phase and unwrapping formulas, frame requirements and their error messages."""
import numpy as np
import pytest
import trimesh

from slwarp.decode import METHODS, MissingFrames, decode, finalize_positions
from slwarp.scans.roles import describe_roles, resolve_roles
from slwarp.decode.gray import HOW_EXTRAPOLATED, HOW_INTERPOLATED, GrayTable
from slwarp.decode.phase import (NumberTheoreticTable, coarse_position, unwrap_number_theoretic,
                                 unwrap_with_reference, wrapped_phase, wrapped_position)
from slwarp.scans.patterns import gray_code, named_set, phase_shift
from slwarp.sim.rigs import make_rig
from slwarp.scans.scan import Scan
from slwarp.sim.scenes import SceneObject
from slwarp.sim.simulate import SimOptions, simulate, simulate_scene

IDEAL = SimOptions(noise=False, defocus=False, gamma=1.0, bits=0)
# every code and phase set of the baselines in one scan; gray10inv's first 7 bits are the gt set's gray7inv
# (a prefix of a Gray code is the shorter code), so the duplicate names hold the same patterns
PLANE_SETS = "gray10inv+gt+cgc6+cgc7+hpmp6+npmp6+ps4+whiteblack+grayrow8inv"


def tilted_plane(z0=700.0, rx=-10.0, ry=20.0, albedo=0.6):
    import trimesh.transformations as tf

    m = trimesh.Trimesh([[-3000, -3000, 0], [3000, -3000, 0], [3000, 3000, 0], [-3000, 3000, 0]], [[0, 2, 1], [0, 3, 2]])
    T = tf.euler_matrix(np.radians(rx), np.radians(ry), 0.0, "sxyz")
    T[:3, 3] = [0.0, 0.0, z0]
    m.apply_transform(T)
    return SceneObject("plane", m, albedo)


def true_projector_coords(scan):
    """[H, W, 2] projector pixel of each camera pixel's GT surface point (NaN where no hit)."""
    cam, proj = scan.camera, scan.projector
    d = cam.pixel_to_ray(cam.pixel_grid())
    X = d * (scan.gt_depth / d[..., 2])[..., None]
    return proj.project_camera_points(X)


@pytest.fixture(scope="module")
def plane_scan():
    cam, proj = make_rig("small")
    return simulate([tilted_plane()], cam, proj, named_set(PLANE_SETS, proj.width, proj.height), IDEAL, device="cpu")


@pytest.fixture(scope="module")
def plane_truth(plane_scan):
    uv = true_projector_coords(plane_scan)
    p = plane_scan.projector
    # The simulator samples patterns bilinearly with zero outside the projector image, so the outermost
    # pixel of each side does not show the ideal pattern; everywhere else it does.
    inner = (uv[..., 0] > 1) & (uv[..., 0] < p.width - 2) & (uv[..., 1] > 1) & (uv[..., 1] < p.height - 2)
    sel = plane_scan.mask & inner
    assert sel.mean() > 0.8
    return uv, sel


# ----------------------------------------------------------------------------------------------
# code tables


@pytest.mark.parametrize("size,bits,stripes,width", [(1280, 7, 128, 10), (1024, 10, 1024, 1), (640, 7, 128, 5)])
def test_gray_table_from_our_patterns(size, bits, stripes, width):
    ps = gray_code(size, 8, bits)
    t = GrayTable.from_patterns(ps.patterns, "col", ps.names)
    assert len(t.start) == stripes and t.max_width == width
    s = np.arange(stripes)
    assert np.array_equal(t.start, s * width) and np.allclose(t.center, s * width + (width - 1) / 2)
    # the stripe of code g is the one whose Gray code is g
    assert np.array_equal(t.lut[s ^ (s >> 1)], s)


def test_gray_table_rows_uneven_and_prefix():
    # OpenCV's row code: 10 bits over 768 rows, row v has the Gray code of v (stripes 0..767, one row each;
    # slwarp's generator would spread the 1024 stripes over the 768 rows instead)
    v = np.arange(768)
    g = v ^ (v >> 1)
    pats = np.stack([np.broadcast_to(((g >> (9 - k)) & 1)[:, None], (768, 11)) for k in range(10)]).astype(np.float32)
    t = GrayTable.from_patterns(pats, "row")
    assert len(t.start) == 768 and t.max_width == 1 and np.allclose(t.center, v)
    # the 7 most significant bits of that code: 96 stripes of 8 rows
    t7 = GrayTable.from_patterns(pats[:7], "row")
    assert len(t7.start) == 96 and np.allclose(t7.center, np.arange(96) * 8 + 3.5)
    # slwarp's 10-bit code on 768 rows: every row its own stripe too; 7 bits: 6-row stripes
    ps = gray_code(11, 768, 10, axis="row")
    assert len(GrayTable.from_patterns(ps.patterns, "row", ps.names).start) == 768
    assert GrayTable.from_patterns(ps.patterns[:7], "row").max_width == 6
    # a code on 1000 columns (stripes of 7 or 8 px) gets centres of its actual stripes
    ps = gray_code(1000, 4, 7)
    t = GrayTable.from_patterns(ps.patterns, "col")
    s = np.arange(1000) * 128 // 1000
    for k in (0, 5, 127):
        cols = np.flatnonzero(s == k)
        assert t.center[k] == pytest.approx((cols[0] + cols[-1]) / 2)


def test_gray_table_rejects_wrong_axis_and_marks_ambiguous_codes():
    ps = gray_code(64, 32, 4)
    with pytest.raises(ValueError, match="gc_col_b0.*not a row code"):
        GrayTable.from_patterns(ps.patterns, "row", ps.names)
    # a code that appears in two separate runs cannot be decoded
    pats = np.zeros((1, 4, 30), np.float32)
    pats[0, :, 10:20] = 1.0
    t = GrayTable.from_patterns(pats, "col")
    assert t.lut[0] == -1 and t.lut[1] == 1 and t.center[1] == pytest.approx(14.5)


# ----------------------------------------------------------------------------------------------
# noise-free planes: every decoder recovers the true projector column


def test_gc_full_resolution_within_half_pixel(plane_scan, plane_truth):
    uv, sel = plane_truth
    d = decode(plane_scan, "gc")  # 10 column bits on 640 columns: one column per code; 8 row bits
    assert d.extra["bits_col"] == 10 and d.extra["inverses_col"]
    err = np.abs(d.col - uv[..., 0])[sel]
    # 1024 codes on 640 columns skip some codes: where two bits flip between neighbouring columns, a pixel
    # exactly on that boundary (both bits tied) can read a skipped code, which is rightly invalid
    fin = np.isfinite(err)
    assert fin.mean() > 0.999 and err[fin].max() <= 0.5 + 1e-3
    # row code: 8 bits on 400 rows, stripes of 1 or 2 rows: within half a stripe
    err_row = np.abs(d.row - uv[..., 1])[sel]
    fin = np.isfinite(err_row)
    assert fin.mean() > 0.999 and err_row[fin].max() <= 1.0 + 1e-3


@pytest.mark.parametrize("bits", [7, 6])
def test_gc_stripe_centre_within_half_stripe(plane_scan, plane_truth, bits):
    uv, sel = plane_truth
    d = decode(plane_scan, "gc", frames=f"gc_col_b[0-{bits - 1}],white,black")
    half = plane_scan.projector.width / 2**bits / 2  # continuous stripe [a - 0.5, b + 0.5] around (a + b) / 2
    err = np.abs(d.col - uv[..., 0])[sel]
    assert d.extra["bits_col"] == bits and not d.extra["inverses_col"] and d.row is None
    assert np.isfinite(err).all() and err.max() <= half + 1e-3


@pytest.mark.parametrize("frames", ["gc_col_b[0-6],gc_col_b[0-6]_inv", "gc_col_b[0-6],white,black", "gc_col_b[0-6]"])
def test_gc_interp_within_half_pixel(plane_scan, plane_truth, frames):
    """With inverses, with the white/black threshold and with the (max + min) / 2 threshold."""
    uv, sel = plane_truth
    d = decode(plane_scan, "gc-interp", frames=frames)
    err = np.abs(d.col - uv[..., 0])
    how = d.extra["how_col"]
    inter = sel & (how == HOW_INTERPOLATED)
    if frames == "gc_col_b[0-6]":
        # without inverses or white/black the threshold is (max + min) / 2 of the bits: the stripes whose
        # bits are all equal (stripe 0: all off; stripe 85: Gray code 1111111) have no contrast
        stripe = np.clip(np.rint(uv[..., 0]), 0, 639).astype(int) * 128 // 640
        sel = sel & (stripe != 0) & (stripe != 85)
    assert inter.sum() > 0.9 * sel.sum()
    # the small rig's camera pixel spans ~1.8 projector px, so a sharp edge is located within ~0.4 px
    assert err[inter].max() < 0.5
    # at the image borders, runs continue the slope of their neighbouring run; a stripe is only ~3 camera
    # px wide on the small rig, so that slope is rough (about 1 px over a stripe at worst)
    ext = sel & (how == HOW_EXTRAPOLATED)
    assert ext.any() and err[ext].max() < 1.25 and err[ext].mean() < 0.5
    assert np.isfinite(err[sel]).all() and err[sel].max() <= 2.5 + 1e-3


def test_gc_interp_row_code_along_camera_columns(plane_scan, plane_truth):
    uv, sel = plane_truth
    d = decode(plane_scan, "gc-interp", frames="gc_row_b[0-5],gc_row_b[0-5]_inv")
    assert d.col is None
    inter = sel & (d.extra["how_row"] == HOW_INTERPOLATED)
    assert inter.sum() > 0.9 * sel.sum()
    assert np.abs(d.row - uv[..., 1])[inter].max() < 0.5


@pytest.mark.parametrize("method,frames", [
    ("ps", None),
    ("cgc", "gc_col_b[0-2],ps_col_p160_*"),  # cgc6 on 640 columns: period W/4
    ("cgc", None),  # picks the most Gray code bits with a matching 3-step set: cgc7, period W/8
    ("hpmp", None),
    ("npmp", None),
    ("gt", "gc_col_b[0-6],gc_col_b[0-6]_inv,ps_col_p40_*"),
])
def test_phase_methods_within_005_px(plane_scan, plane_truth, method, frames):
    uv, sel = plane_truth
    d = decode(plane_scan, method, frames=frames)
    err = np.abs(d.col - uv[..., 0])[sel]
    # bilinear sampling of a sampled sinusoid shifts its phase by ~0.016 (2 pi / P)^3 rad: < 1e-3 px here
    assert np.isfinite(err).all() and err.max() < 0.05
    if method == "cgc" and frames is None:
        assert d.extra["bits"] == 4 and d.extra["periods"] == [80.0]


def test_gt_uses_all_gray_bits_and_inverses(plane_scan):
    d = decode(plane_scan, "gt")
    assert d.extra["bits"] == 10 and "gc_col_b9_inv" in d.frames and "ps_col_p40_s3of4" in d.frames


# ----------------------------------------------------------------------------------------------
# noise on: invalid pixels are NaN, valid ones plausible


@pytest.fixture(scope="module")
def noisy_scan():
    return simulate_scene("torus", "gt+cgc6+cgc7+hpmp6+npmp6+ps4+whiteblack", "small", SimOptions(seed=3), device="cpu")


@pytest.mark.parametrize("method,frames", [
    ("gc", "gc_col_b[0-6],gc_col_b[0-6]_inv"), ("gc-interp", "gc_col_b[0-6]"), ("gc-interp", "gc_col_b[0-5],white,black"),
    ("ps", None), ("cgc", "gc_col_b[0-2],ps_col_p160_*"), ("cgc", "gc_col_b[0-3],ps_col_p80_*"),
    ("hpmp", None), ("npmp", None), ("gt", None),
])
def test_noisy_invalid_is_nan_never_garbage(noisy_scan, method, frames):
    scan = noisy_scan
    d = decode(scan, method, frames=frames)
    col, W = d.col, scan.projector.width
    assert col.dtype == np.float64 and col.shape == scan.gt_depth.shape
    assert np.array_equal(d.valid, np.isfinite(col))
    assert not np.isinf(col).any()
    assert np.all((col[d.valid] >= -0.5) & (col[d.valid] <= W - 0.5))
    # the background (no hit) and the shadows (hit, not lit) are invalid
    unlit = ~scan.mask
    assert unlit.sum() > 2000
    assert d.valid[unlit].mean() < 0.01
    # and the lit pixels mostly valid and right
    uv = true_projector_coords(scan)
    lit = scan.mask
    assert d.valid[lit].mean() > 0.9
    err = np.abs(col - uv[..., 0])[lit & d.valid]
    # gc: the stripe centre of 5 px stripes; ps: one 640 px period, so phase noise is 16x that of 40 px
    limit = {"gc": 3.0, "ps": 5.0}.get(method, 1.0)
    assert np.median(err) < limit


# ----------------------------------------------------------------------------------------------
# formulas


@pytest.mark.parametrize("steps", [3, 4, 7])
def test_wrapped_phase_recovers_phase_offset_modulation(steps):
    rng = np.random.default_rng(steps)
    phi = rng.uniform(0, 2 * np.pi, (5, 7))
    A, B = rng.uniform(0.2, 0.5, phi.shape), rng.uniform(0.05, 0.2, phi.shape)
    imgs = np.stack([A + B * np.cos(phi - 2 * np.pi * k / steps) for k in range(steps)])
    p, a, b = wrapped_phase(imgs)
    assert np.allclose(p, phi, atol=1e-12) and np.allclose(a, A) and np.allclose(b, B)
    assert np.all((p >= 0) & (p < 2 * np.pi))


def test_pattern_contract_matches_phase_model():
    """The generator's phase patterns decode to phi = 2 pi u / P at every projector column."""
    ps = phase_shift(200, 2, 40.0, 4)
    phi, _, mod = wrapped_phase(ps.patterns[:, :1, :].astype(np.float64))
    u = np.arange(200.0)
    assert np.allclose(wrapped_position(phi, 40.0)[0], np.mod(u, 40.0), atol=1e-4)
    assert np.allclose(mod, 0.5, atol=1e-6)


def test_unwrap_with_reference_tolerates_quarter_period():
    P = 40.0
    u = np.linspace(-0.5, 1279.5, 20001)
    uw = np.mod(u, P)
    for off in (-0.49 * P, -P / 4, 0.0, P / 4, 0.49 * P):
        assert np.allclose(unwrap_with_reference(uw, u + off, P), u, atol=1e-9)
    assert np.isnan(unwrap_with_reference(np.array([np.nan]), np.array([3.0]), P)).all()


def test_coarse_position_covers_pixel_area():
    W = 1280.0
    u = np.array([-0.5, -0.2, 0.0, 639.5, 1279.4])
    phi = np.mod(2 * np.pi * u / W, 2 * np.pi)
    assert np.allclose(coarse_position(phi, W), u)


def test_number_theoretic_unwrapping():
    table = NumberTheoreticTable(48, 70, 1280)
    assert table.g == 2
    u = np.linspace(-0.5, 1279.5, 40001)
    u1, u2 = np.mod(u, 48), np.mod(u, 70)
    est, dis = unwrap_number_theoretic(u1, u2, 48, 70, 1280, table)
    assert np.allclose(est, u, atol=1e-9) and np.allclose(dis, 0, atol=1e-9)
    # disagreement below g / 2 is absorbed (the estimate is the weighted mean), noise on one set only
    rng = np.random.default_rng(0)
    noise = rng.uniform(-0.9, 0.9, u.shape)
    est, _ = unwrap_number_theoretic(np.mod(u + noise, 48), u2, 48, 70, 1280, table)
    w1 = (1 / 48**2) / (1 / 48**2 + 1 / 70**2)
    assert np.allclose(est, u + w1 * noise, atol=1e-6)
    # a disagreement beyond g / 2 picks no pair (NaN) or a wrong one, which is far away: for 48 / 70 px the
    # neighbouring entries of a pair's are 16 / 11 or 19 / 13 periods away (24 * 16 - 35 * 11 = -1,
    # 24 * 19 - 35 * 13 = 1), i.e. ~770 or ~910 px. That is N-PMP's failure mode; the triangulated points
    # then leave the working volume.
    est, _ = unwrap_number_theoretic(np.mod(u + 1.5, 48), u2, 48, 70, 1280, table)
    fin = np.isfinite(est)
    assert not np.isinf(est).any() and 0.2 < (~fin).mean() < 0.8
    assert np.all(np.abs(est - u)[fin] > 760)
    with pytest.raises(ValueError, match="unambiguous"):
        NumberTheoreticTable(48, 72, 1280)


def test_finalize_positions():
    u = np.array([-2.0, -0.8, -0.5, 10.0, 639.7, 641.0, np.inf, np.nan])
    out = finalize_positions(u, 640)
    assert np.allclose(out[1:5], [-0.5, -0.5, 10.0, 639.5])
    assert np.isnan(out[[0, 5, 6, 7]]).all()


# ----------------------------------------------------------------------------------------------
# frame requirements


def _fake_scan(pattern_spec: str):
    cam, proj = make_rig("small")
    ps = named_set(pattern_spec, proj.width, proj.height)
    imgs = np.random.default_rng(0).uniform(0, 1, (len(ps), cam.height, cam.width)).astype(np.float32)
    return Scan(cam, proj, imgs, ps.patterns, ps.names)


@pytest.mark.parametrize("method,needs", [
    ("cgc", ["gray:col:bit=0-2", "3-step phase shift", "W/4 = 160 px", "phase:col:period=160"]),
    ("hpmp", ["phase:col:period=640", "phase:col:period=80", "3-step"]),
    ("npmp", ["phase:col:period=48", "phase:col:period=70"]),
    ("gt", ["gray:col:bit=0-6", "with inverses", "gc_col_b0..gc_col_b6", "phase:col:period=40"]),
    ("ps", ["phase:col:period=640", "width", "ps_col_p640_s0ofN"]),
])
def test_missing_frames_message_names_needs_and_haves(method, needs):
    scan = _fake_scan("gray7")
    with pytest.raises(MissingFrames) as e:
        decode(scan, method)
    msg = str(e.value)
    assert msg.startswith(f"method {method} needs")
    for n in needs:
        assert n in msg
    assert msg.endswith("the scan has: gray:col:bit=0-6")


def test_missing_gray_code_and_unknown_method():
    scan = _fake_scan("npmp6")
    with pytest.raises(MissingFrames, match="gc needs Gray code frames: roles gray:col:bit=0"):
        decode(scan, "gc")
    with pytest.raises(ValueError, match="unknown decoding method 'zebra'"):
        decode(scan, "zebra")
    assert set(METHODS) == {"gc", "gc-interp", "ps", "cgc", "hpmp", "npmp", "gt"}


def test_wrong_phase_pattern_is_reported():
    scan = _fake_scan("ps4")
    scan.patterns[1] = scan.patterns[1] ** 3  # not a sinusoid any more
    with pytest.raises(ValueError, match="ps_col_p640_s1of4 is not a sinusoid of period 640 px along the projector columns"):
        decode(scan, "ps")
    scan = _fake_scan("npmp6")  # a role whose period is not the pattern's
    renamed = [n.replace("ps_col_p48", "p48") for n in scan.names]
    declared = {f"p48_s{k}of3": {"kind": "phase", "axis": "col", "period": 50.0, "step": k, "steps": 3} for k in range(3)}
    bad = Scan(scan.camera, scan.projector, scan.images, scan.patterns, renamed, declared_roles=declared)
    with pytest.raises(ValueError, match="frame p48_s0of3 is not a sinusoid of period 50 px"):
        decode(bad, "npmp", periods=(50, 70))


def test_phase_shifts_are_measured_from_the_patterns(plane_scan, plane_truth):
    """Another N-step convention (the steps in reverse order, as the NeSS authors' patterns run) decodes to
    the same positions: each step's shift comes from its pattern, not from a formula."""
    uv, sel = plane_truth
    sub = plane_scan.select("phase:col:period=640:steps=4")
    order = [3, 2, 1, 0]  # the frame of role step k shows the pattern of step 3 - k
    flipped = Scan(sub.camera, sub.projector, sub.images[order], sub.patterns[order], [f"f{k}" for k in range(4)],
                   declared_roles={f"f{k}": {"kind": "phase", "axis": "col", "period": 640, "step": k, "steps": 4}
                                   for k in range(4)})
    d = decode(flipped, "ps")
    err = np.abs(d.col - uv[..., 0])[sel]
    assert np.isfinite(err).all() and err.max() < 0.05


def test_describe_roles():
    names = named_set("gray7inv+npmp6+whiteblack+random6", 640, 400).names + ["frame_a", "frame_b"]
    assert describe_roles(names, resolve_roles(names)) == (
        "gray:col:bit=0-6 (+inv), phase:col:period=48:steps=3 (step=0-2), phase:col:period=70:steps=3 (step=0-2), "
        "white, black, random:size=20 x2, random:size=10 x2, random:size=5 x2, no role (2 frames: frame_a, frame_b)")
