"""The virtual scanner: exact ground truth, shadows, the image formation model, the CLI."""
from dataclasses import asdict

import numpy as np
import pytest
import trimesh

from slwarp.cli import main as cli_main
from slwarp.scans.patterns import named_set, random_binary
from slwarp.sim.rigs import make_rig
from slwarp.scans.scan import load_scan
from slwarp.sim.scenes import SCENE_NAMES, SIX_SCENES, SceneObject, build_scene
from slwarp.sim.simulate import CAMERA_MODELS, SimOptions, camera_model, camera_response, simulate, simulate_scene

IDEAL = SimOptions(noise=False, defocus=False, gamma=1.0, bits=0)


def plane(z, albedo=0.6, **texture):
    m = trimesh.Trimesh([[-2000, -2000, z], [2000, -2000, z], [2000, 2000, z], [-2000, 2000, z]], [[0, 2, 1], [0, 3, 2]])
    return SceneObject("plane", m, albedo, **texture)


def bilinear_zero(img, u, v):
    h, w = img.shape
    u0, v0 = np.floor(u).astype(int), np.floor(v).astype(int)
    fu, fv = u - u0, v - v0
    out = np.zeros_like(u)
    for dy in (0, 1):
        for dx in (0, 1):
            x, y = u0 + dx, v0 + dy
            ok = (x >= 0) & (x < w) & (y >= 0) & (y < h)
            wgt = (fu if dx else 1 - fu) * (fv if dy else 1 - fv)
            out[ok] += wgt[ok] * img[y[ok], x[ok]]
    return out


def test_plane_ground_truth_exact(device):
    cam, proj = make_rig("small")
    pats = random_binary(proj.width, proj.height, per_scale=1)
    scan = simulate([plane(612.5)], cam, proj, pats, IDEAL, device=device)
    assert np.isfinite(scan.gt_depth).all()
    assert np.abs(scan.gt_depth - 612.5).max() < 1e-3


def test_sphere_ground_truth_matches_analytic_intersection(device):
    cam, proj = make_rig("small")
    center, r = np.array([10.0, -5.0, 300.0]), 20.0
    sphere = trimesh.creation.icosphere(subdivisions=7, radius=r)
    sphere.apply_translation(center)
    scan = simulate([SceneObject("s", sphere), plane(700.0)], cam, proj, random_binary(proj.width, proj.height, per_scale=1), IDEAL, device=device)
    d = cam.pixel_to_ray(cam.pixel_grid())
    b = d @ center
    disc = b**2 - (center @ center - r * r)
    hit = disc > 0
    t = b - np.sqrt(np.where(hit, disc, 0))
    analytic = t * d[..., 2]
    # grazing rays magnify the tessellation error: compare where the ray meets the sphere at > 25 deg
    x = d * t[..., None]
    cos_inc = np.abs(((x - center) / r * d).sum(-1))
    sel = hit & (cos_inc > 0.42)
    assert sel.sum() > 1000
    assert np.abs(scan.gt_depth[sel] - analytic[sel]).max() < 1e-3
    assert np.all(np.abs(scan.gt_depth[~hit] - 700.0) < 1e-2)  # the rest hits the plane behind it


def test_point_hidden_from_projector_is_unlit(device):
    cam, proj = make_rig("small")
    c_p = proj.center
    wall_point = np.array([0.0, 0.0, 800.0])
    blocker = trimesh.creation.icosphere(subdivisions=3, radius=12.0)
    blocker.apply_translation(c_p + 0.5 * (wall_point - c_p))  # on the line from the wall point to the projector
    scan = simulate([plane(800.0), SceneObject("blocker", blocker)], cam, proj, named_set("whiteblack", proj.width, proj.height), IDEAL, device=device)
    u, v = np.round(cam.project(wall_point[None])[0]).astype(int)
    assert abs(scan.gt_depth[v, u] - 800.0) < 1e-3  # the camera sees the wall there
    assert not scan.mask[v, u]  # but the projector does not light it
    white = scan.image("white")
    assert white[v, u] == pytest.approx(IDEAL.ambient * 0.6, abs=1e-6)
    assert scan.mask[v, u + 40] and white[v, u + 40] > 0.2  # nearby wall is lit


def test_intensity_model_without_noise_gamma_defocus(device):
    cam, proj = make_rig("small")
    pats = named_set("random6+ps4", proj.width, proj.height)
    albedo, z = 0.55, 640.0
    opts = IDEAL
    scan = simulate([plane(z, albedo)], cam, proj, pats, opts, device=device)
    d = cam.pixel_to_ray(cam.pixel_grid())
    x = d * (z / d[..., 2:3])
    to_p = proj.center - x
    dist = np.linalg.norm(to_p, axis=-1)
    cos = (to_p / dist[..., None]) @ np.array([0.0, 0.0, -1.0])
    shade = albedo * cos * (opts.ref_dist / dist) ** 2
    uv = proj.project_camera_points(x)
    lit = scan.mask
    assert lit.mean() > 0.5
    for i in range(len(pats)):
        expect = opts.gain * shade * bilinear_zero(pats.patterns[i].astype(np.float64), uv[..., 0], uv[..., 1]) + opts.ambient * albedo
        # float32 hit points and projections (~1e-4 px) times pattern slopes of up to 1 per px
        assert np.abs(scan.images[i][lit] - expect[lit]).max() < 2e-4


def test_effects_change_images_and_seed_repeats():
    cam, proj = make_rig("small")
    pats = random_binary(proj.width, proj.height, per_scale=1)
    objs = [plane(700.0)]
    a = simulate(objs, cam, proj, pats, SimOptions(seed=1))
    b = simulate(objs, cam, proj, pats, SimOptions(seed=1))
    c = simulate(objs, cam, proj, pats, SimOptions(seed=2))
    ideal = simulate(objs, cam, proj, pats, IDEAL)
    assert np.array_equal(a.images, b.images)
    assert not np.array_equal(a.images, c.images)
    assert np.all(np.abs(a.images * 255 - np.round(a.images * 255)) < 1e-3)  # 8-bit quantised
    noise = (a.images - ideal.images)[:, a.mask]
    assert 0.002 < noise.std() < 0.05


def test_cli_simulate_every_scene_and_pattern_set(tmp_path, capsys):
    sets = "random6+random9+gray6+gray7+gray7inv+gt+cgc6+cgc7+hpmp6+npmp6+whiteblack"
    for scene in SCENE_NAMES:
        out = tmp_path / scene
        assert cli_main(["simulate", "--scene", scene, "--patterns", sets, "--rig", "small", "--out", str(out)]) == 0
        scan = load_scan(out)
        assert scan.gt_depth is not None and scan.mask is not None and 0.5 < scan.mask.mean() < 0.95
        assert cli_main(["info", str(out)]) == 0
        assert (out / "preview.png").is_file()
    out = capsys.readouterr().out
    assert "ground truth depth: yes" in out


def test_cli_simulate_user_mesh(tmp_path):
    mesh = trimesh.creation.box((300.0, 300.0, 50.0))
    mesh.apply_translation((0, 0, 700.0))
    mesh.export(tmp_path / "box.ply")
    assert cli_main(["simulate", "--mesh", str(tmp_path / "box.ply"), "--patterns", "gray6", "--rig", "small",
                     "--no-noise", "--out", str(tmp_path / "scan")]) == 0
    scan = load_scan(tmp_path / "scan")
    assert np.nanmin(scan.gt_depth) == pytest.approx(675.0, abs=1e-3)


def test_cli_simulate_bad_input(tmp_path, capsys):
    assert cli_main(["simulate", "--scene", "nope", "--rig", "small", "--out", str(tmp_path / "x")]) == 2
    assert "unknown scene" in capsys.readouterr().err
    assert cli_main(["simulate", "--mesh", str(tmp_path / "missing.ply"), "--out", str(tmp_path / "x")]) == 2
    assert "mesh not found" in capsys.readouterr().err
    assert cli_main(["simulate", "--scene", "bunny", "--patterns", "zebra", "--out", str(tmp_path / "x")]) == 2
    assert "unknown pattern set" in capsys.readouterr().err
    assert cli_main(["simulate", "--scene", "bunny", "--halo", "2", "--out", str(tmp_path / "x")]) == 2
    assert "halo must be in [0, 1)" in capsys.readouterr().err and not (tmp_path / "x").exists()
    assert cli_main(["simulate", "--scene", "bunny", "--camera", "film", "--out", str(tmp_path / "x")]) == 2
    assert "unknown camera model 'film'" in capsys.readouterr().err and not (tmp_path / "x").exists()


def test_cli_simulate_camera_model_and_the_options_over_it(tmp_path):
    """--camera takes a named model's optics; an option given on the command line overrides the model's, the others
    keep it (scan.yaml records the simulator's settings)."""
    assert cli_main(["simulate", "--scene", "bunny", "--rig", "small", "--patterns", "gray3", "--camera", "procam",
                     "--black-level", "0.05", "--no-noise", "--out", str(tmp_path / "scan")]) == 0
    sim = load_scan(tmp_path / "scan").meta["simulator"]
    procam = camera_model("procam")
    assert sim["black_level"] == 0.05 and sim["noise"] is False
    assert (sim["near_halo"], sim["halo"], sim["supersample"]) == (procam.near_halo, procam.halo, procam.supersample)
    assert cli_main(["simulate", "--scene", "bunny", "--rig", "small", "--patterns", "gray3", "--out",
                     str(tmp_path / "plain")]) == 0
    plain = load_scan(tmp_path / "plain").meta["simulator"]
    assert plain == {**asdict(SimOptions()), "seed": 0}


# --- textures, pixel integration, lens blur, camera response ---------------------------------------

FLAT = SimOptions(noise=False, defocus=False, shading=False, bits=0)  # white frame = (gain + ambient) * albedo


def checker_albedo(x, y, albedo, amplitude, period):
    """Hand reference: squares of period / 2 mm over camera x and y, the square at the origin's + side dark."""
    parity = (np.floor(x / (period / 2)) + np.floor(y / (period / 2))) % 2
    return albedo * (1 - amplitude + amplitude * parity)


def plane_points(cam, z):
    d = cam.pixel_to_ray(cam.pixel_grid())
    return d * (z / d[..., 2:3])


def fully_lit(cam, proj, z, margin=2.0):
    """Pixels of a plane at z whose point projects `margin` projector px inside the projector image (the
    white frame fades over the last pixel, where bilinear taps leave the image)."""
    uv = proj.project_camera_points(plane_points(cam, z))
    return ((uv[..., 0] > margin) & (uv[..., 0] < proj.width - 1 - margin)
            & (uv[..., 1] > margin) & (uv[..., 1] < proj.height - 1 - margin))


def test_checker_texture_albedo(device):
    cam, proj = make_rig("small")
    z, period = 700.0, 40.0
    scan = simulate([plane(z, 0.7, texture=0.9, texture_period=period, texture_kind="checker")], cam, proj,
                    named_set("whiteblack", proj.width, proj.height), FLAT, device=device)
    x = plane_points(cam, z)
    expect = (FLAT.gain + FLAT.ambient) * checker_albedo(x[..., 0], x[..., 1], 0.7, 0.9, period)
    cell = period / 2
    dist_to_edge = np.minimum(np.abs(x[..., 0] / cell - np.round(x[..., 0] / cell)),
                              np.abs(x[..., 1] / cell - np.round(x[..., 1] / cell))) * cell
    sel = scan.mask & fully_lit(cam, proj, z) & (dist_to_edge > 0.01)  # float32 points: not within 10 um of an edge
    white = scan.image("white")
    assert sel.mean() > 0.5
    assert np.abs(white[sel] - expect[sel]).max() < 1e-5
    assert np.unique(np.round(white[sel] / (FLAT.gain + FLAT.ambient), 4)) == pytest.approx([0.07, 0.7])  # 10:1


def test_supersampling_integrates_each_pixel_and_keeps_the_centre_ground_truth(device):
    cam, proj = make_rig("small")
    z, period = 700.0, 10.0  # 5 mm squares: 3 px on the small rig, so many pixels straddle an edge
    objs = [plane(z, 0.7, texture=0.9, texture_period=period, texture_kind="checker")]
    pats = named_set("whiteblack", proj.width, proj.height)
    one = simulate(objs, cam, proj, pats, FLAT, device=device)
    k = 3
    integ = simulate(objs, cam, proj, pats, SimOptions(**{**FLAT.__dict__, "supersample": k}), device=device)
    assert np.array_equal(integ.gt_depth, one.gt_depth) and np.array_equal(integ.mask, one.mask)
    x = plane_points(cam.scaled(k), z)  # the k x k rays of each pixel
    fine = checker_albedo(x[..., 0], x[..., 1], 0.7, 0.9, period)
    expect = (FLAT.gain + FLAT.ambient) * fine.reshape(cam.height, k, cam.width, k).mean(axis=(1, 3))
    white = integ.image("white")
    sel = one.mask & fully_lit(cam, proj, z)
    err = np.abs(white[sel] - expect[sel])
    # float32 hit points put a sub-ray lying on an edge (within ~1e-5 mm) on the other side, rarely
    one_ray = (FLAT.gain + FLAT.ambient) * (0.7 - 0.07) / k**2
    assert (err > 1e-5).mean() < 0.01 and err.max() < one_ray + 1e-5
    albedo = white[sel] / (FLAT.gain + FLAT.ambient)
    mixed = (np.abs(albedo - 0.07) > 1e-3) & (np.abs(albedo - 0.7) > 1e-3)
    assert mixed.mean() > 0.3  # one ray per pixel would never mix the two albedos


def test_camera_blur_is_a_gaussian_psf(device):
    from scipy.ndimage import gaussian_filter

    cam, proj = make_rig("small")
    objs = [plane(700.0, 0.7, texture=0.9, texture_period=20.0, texture_kind="checker")]
    pats = named_set("whiteblack", proj.width, proj.height)
    sharp = simulate(objs, cam, proj, pats, FLAT, device=device)
    blurred = simulate(objs, cam, proj, pats, SimOptions(**{**FLAT.__dict__, "camera_blur": 1.5}), device=device)
    ref = gaussian_filter(sharp.image("white").astype(np.float64), 1.5, mode="reflect", truncate=4.0)
    sel = fully_lit(cam, proj, 700.0, margin=12.0)  # the PSF's support (6 px) stays on the lit plane
    assert np.abs(blurred.image("white")[sel] - ref[sel]).max() < 2e-3
    assert np.abs(blurred.image("white") - sharp.image("white"))[sel].max() > 0.1  # the edges did blur


def test_camera_response_curves():
    lin = np.array([-0.1, 0.0, 0.002, 0.25, 0.5, 1.0, 1.3])
    srgb = camera_response(lin, SimOptions(response="srgb"))
    # sRGB by hand: 12.92 x below 0.0031308, else 1.055 x^(1/2.4) - 0.055; clipped to [0, 1] first
    assert srgb == pytest.approx([0.0, 0.0, 0.02584, 0.537099, 0.735357, 1.0, 1.0], abs=2e-6)
    g = camera_response(lin, SimOptions(gamma=2.2))
    assert g == pytest.approx([0.0, 0.0, 0.002 ** (1 / 2.2), 0.25 ** (1 / 2.2), 0.5 ** (1 / 2.2), 1.0, 1.0])
    assert camera_response(lin, SimOptions()) == pytest.approx(np.clip(lin, 0, 1))


def test_gamma_images_are_the_linear_images_through_the_curve(device):
    cam, proj = make_rig("small")
    pats = random_binary(proj.width, proj.height, per_scale=1)
    objs = [plane(700.0)]
    lin = simulate(objs, cam, proj, pats, IDEAL, device=device)
    for opts, curve in [(SimOptions(**{**IDEAL.__dict__, "gamma": 2.2}), lambda i: i ** (1 / 2.2)),
                        (SimOptions(**{**IDEAL.__dict__, "response": "srgb"}),
                         lambda i: np.where(i <= 0.0031308, 12.92 * i, 1.055 * i ** (1 / 2.4) - 0.055))]:
        scan = simulate(objs, cam, proj, pats, opts, device=device)
        assert np.abs(scan.images - curve(lin.images.astype(np.float64))).max() < 1e-5


def test_sim_options_and_scene_objects_reject_bad_values():
    for bad, msg in [({"supersample": 2}, "odd"), ({"supersample": 0}, "odd"), ({"camera_blur": -1.0}, "camera_blur"),
                     ({"response": "log"}, "response"), ({"response": "srgb", "gamma": 2.2}, "gamma must stay 1"),
                     ({"gamma": 0.0}, "gamma"), ({"bits": 12}, "bits")]:
        with pytest.raises(ValueError, match=msg):
            SimOptions(**bad)
    with pytest.raises(ValueError, match="texture_kind"):
        SceneObject("x", None, texture_kind="stripes")
    with pytest.raises(ValueError, match="texture_period"):
        SceneObject("x", None, texture=0.5, texture_period=0.0)
    with pytest.raises(ValueError, match="unknown camera model"):
        camera_model("film")


def test_camera_models_and_named_scenes():
    assert SCENE_NAMES[:6] == SIX_SCENES == ("spheres", "torus", "boxes", "bunny", "vase", "steps")
    assert camera_model("linear") == SimOptions()  # the scanner the six-scene results were measured with
    for name in CAMERA_MODELS:
        camera_model(name)
    assert camera_model("gamma", seed=3).gamma == 2.2 and camera_model("gamma", seed=3).seed == 3
    scan = simulate_scene("checker", "whiteblack", rig="small", options="srgb", device="cpu")
    assert scan.meta["camera_model"] == "srgb" and scan.meta["simulator"]["response"] == "srgb"


def test_rods_scene_has_thin_rods_in_front():
    objs = {o.name: o for o in build_scene("rods")}
    rods = [o for n, o in objs.items() if n.startswith("rod_")]
    assert len(rods) >= 5
    for rod in rods:
        v = np.asarray(rod.mesh.vertices)
        # a closed cylinder: its two cap centres on the axis, every other vertex 1.25 mm from it
        axis = rod.mesh.principal_inertia_vectors[0]
        r = np.sort(np.linalg.norm(np.cross(v - v.mean(0), axis), axis=1))
        assert r[:2] == pytest.approx(0.0, abs=1e-6) and r[2:] == pytest.approx(1.25, abs=1e-6), rod.name
        assert np.ptp(v @ axis) > 400.0  # long enough to cross the field of view
        assert v[:, 2].max() < min(np.asarray(o.mesh.vertices)[:, 2].min() for n, o in objs.items() if n.startswith("sphere"))
    cam, proj = make_rig("small")
    scan = simulate(list(objs.values()), cam, proj, named_set("whiteblack", proj.width, proj.height), IDEAL)
    on_rod = scan.gt_depth < 685.0
    # the rods cover a thin share of the image: about (number x length x 2.5 mm) / footprint^2 pixels
    assert 0.005 < on_rod.mean() < 0.05


def test_waves_scene_is_a_closed_sheet_whose_front_follows_its_two_sines():
    objs = {o.name: o for o in build_scene("waves")}
    sheet = objs["waves"].mesh
    assert sheet.is_watertight and sheet.is_winding_consistent and sheet.volume > 0
    cam, proj = make_rig("small")
    scan = simulate(list(objs.values()), cam, proj, named_set("whiteblack", proj.width, proj.height), IDEAL)
    # the ground truth at every pixel whose ray meets the front: z = 700 + 15 sin(2 pi x / 120) + 10 sin(2 pi y / 90)
    from slwarp.neural.depth_maps import depth_to_points

    z = scan.gt_depth
    x, y, _ = depth_to_points(z, cam).T  # the pixel's ray (lens distortion included) at the found depth
    z = z[np.isfinite(z)]
    front = (z < 740.0) & (np.abs(x) < 270.0) & (np.abs(y) < 210.0)
    assert front.sum() > 0.8 * cam.width * cam.height  # the sheet fills most of the view
    model = 700.0 + 15.0 * np.sin(2 * np.pi * x / 120.0) + 10.0 * np.sin(2 * np.pi * y / 90.0)
    assert np.percentile(np.abs(z - model)[front], 99) < 0.1  # flat triangles 2 mm wide between the vertices
    assert z[front].min() < 680.0 and z[front].max() > 720.0


def test_lens_halo_lifts_dark_stripes_near_bright_ones_and_keeps_the_light(device):
    """SimOptions.halo: the projected pattern is (1 - halo) x itself + halo x its blur over halo_sigma projector px
    (scans.scanner.with_halo, the model the neural method shares): on a flat plate a dark stripe's pixels rise near
    a bright stripe, the edges lose their full step, and the mean light is kept."""
    cam, proj = make_rig("small")
    pats = named_set("gray3", proj.width, proj.height)
    objs = [plane(700.0, 0.7)]
    sharp = simulate(objs, cam, proj, pats, FLAT, device=device)
    halo = simulate(objs, cam, proj, pats, SimOptions(**{**FLAT.__dict__, "halo": 0.2, "halo_sigma": 20.0}),
                    device=device)
    sel = sharp.mask & fully_lit(cam, proj, 700.0, margin=30.0)
    for i in range(len(sharp)):
        a, b = sharp.images[i][sel], halo.images[i][sel]
        dark, bright = a <= a.min() + 1e-4, a >= a.max() - 1e-4  # fully dark and fully lit pixels without halo
        assert b[dark].max() > a[dark].max() + 0.03 and b[bright].min() < a[bright].min() - 0.03  # near the edges
        assert abs(b.mean() - a.mean()) < 0.02 * a.mean()
    with pytest.raises(ValueError, match="halo"):
        SimOptions(halo=1.0)


def test_near_halo_is_a_second_gaussian_scale_of_the_lens_tail():
    """halo_patterns: (1 - halo - near_halo) P + halo G(halo_sigma) P + near_halo G(near_halo_sigma) P, with
    sampled Gaussians over +-3 sigma and replicated edges; without a near halo it is with_halo itself."""
    from scipy.ndimage import gaussian_filter1d

    from slwarp.scans.scanner import with_halo
    from slwarp.sim.simulate import halo_patterns

    rng = np.random.default_rng(0)
    pats = (rng.random((3, 40, 60)) < 0.5).astype(np.float32)
    assert np.array_equal(halo_patterns(pats, SimOptions(halo=0.1, halo_sigma=7.0)), with_halo(pats, 0.1, 7.0))
    assert np.array_equal(halo_patterns(pats, SimOptions()), pats)
    # a step: columns 0-79 dark, 80-159 lit (constant down the columns, so the 2-D blur is the 1-D one)
    step = np.zeros((1, 30, 160), np.float32)
    step[..., 80:] = 1.0
    both = SimOptions(halo=0.1, halo_sigma=10.0, near_halo=0.15, near_halo_sigma=2.0)
    row = halo_patterns(step, both)[0, 15].astype(np.float64)
    blur = lambda s: gaussian_filter1d(step[0, 15].astype(np.float64), s, mode="nearest", truncate=3.0)  # noqa: E731
    assert np.abs(row - (0.75 * step[0, 15] + 0.1 * blur(10.0) + 0.15 * blur(2.0))).max() < 1e-5
    # the near halo's own tail: light on the dark side next to the edge, taken from the lit side, gone in 5 sigma
    near = row - halo_patterns(step, SimOptions(halo=0.1, halo_sigma=10.0))[0, 15]
    assert near[79] > 0.05 and near[80] < -0.05
    assert np.all(np.diff(near[60:80]) >= 0) and abs(near[69]) < 1e-4 and abs(near[90]) < 1e-4
    # the light is kept: a pattern that is dark within 3 sigma of its border sums to the same
    framed = np.zeros((2, 102, 122), np.float32)  # 31 px of dark around: the far blur reaches 30
    framed[:, 31:-31, 31:-31] = pats[:2]
    out = halo_patterns(framed, both)
    assert out.sum(axis=(1, 2)) == pytest.approx(framed.sum(axis=(1, 2)), rel=1e-5)
    assert np.abs(out - framed).max() > 0.1


def test_sim_options_check_the_near_halo_and_black_level():
    SimOptions(halo=0.5, near_halo=0.49, black_level=0.99)  # the bounds themselves are fine
    for bad, msg in [({"halo": 0.5, "near_halo": 0.5}, "near_halo"), ({"near_halo": -0.1}, "near_halo"),
                     ({"near_halo": 0.1, "near_halo_sigma": 0.0}, "near_halo"), ({"black_level": -0.01}, "black_level"),
                     ({"black_level": 1.0}, "black_level")]:
        with pytest.raises(ValueError, match=msg):
            SimOptions(**bad)
    procam = camera_model("procam")
    assert procam.near_halo + procam.halo < 1 and procam.black_level == 0.02 and procam.defocus_slope == 0.0


def test_black_level_is_added_before_the_response(device):
    lin = np.array([0.0, 0.3, 0.99, 1.2])
    assert camera_response(lin, SimOptions(black_level=0.02)) == pytest.approx([0.02, 0.32, 1.0, 1.0])
    assert camera_response(lin, SimOptions(black_level=0.02, gamma=2.2)) == pytest.approx(
        [0.02 ** (1 / 2.2), 0.32 ** (1 / 2.2), 1.0, 1.0])
    # in a rendered scan: every pixel, lit or not, rises by the black level (the black frame reads it)
    cam, proj = make_rig("small")
    objs = [plane(700.0)]
    pats = named_set("whiteblack", proj.width, proj.height)
    off = simulate(objs, cam, proj, pats, IDEAL, device=device)
    on = simulate(objs, cam, proj, pats, SimOptions(**{**IDEAL.__dict__, "black_level": 0.05}), device=device)
    assert np.abs(on.images - off.images - 0.05).max() < 1e-6
    assert np.abs(on.image("black") - (0.05 + IDEAL.ambient * 0.6)).max() < 1e-6
