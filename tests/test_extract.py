"""Depth-map clean-up at extraction (slwarp.neural.extraction.surface): the neighbourhood stack
(slwarp.neural.depth_maps) and the flying-pixel filter, on hand-made depth maps."""
from types import SimpleNamespace

import numpy as np

from slwarp.neural.config import ExtractionConfig
from slwarp.neural.depth_maps import neighbour_stack
from slwarp.neural.extraction.surface import denoise_depth, flying_pixel_filter, readmit_edge_pixels

CAMERA = SimpleNamespace(fx=500.0, fy=500.0)  # a pixel footprint of 1 mm at 500 mm
# the edge readmission's default bars (the options edge_readmit_support and edge_readmit_confidence)
BAR = dict(min_support=ExtractionConfig().edge_readmit_support, min_confidence=ExtractionConfig().edge_readmit_confidence)


def test_neighbour_stack_holds_the_8_neighbours():
    d = np.arange(9, dtype=np.float32).reshape(3, 3)
    s = neighbour_stack(d)
    assert s.shape == (8, 3, 3)
    np.testing.assert_array_equal(np.sort(s[:, 1, 1]), [0, 1, 2, 3, 5, 6, 7, 8])
    assert np.isnan(s[:, 0, 0]).sum() == 5  # a corner has 3 neighbours inside the image


def test_flying_pixel_filter_drops_both_sides_of_a_jump_and_keeps_a_slope():
    d = np.full((6, 6), 500.0, np.float32)
    d[:, 3:] = 600.0  # a 100 mm jump: 100 footprints
    out = flying_pixel_filter(d, CAMERA, footprints=10.0)
    assert np.isnan(out[:, 2:4]).all()
    assert np.isfinite(out[:, :2]).all() and np.isfinite(out[:, 4:]).all()
    slope = 500.0 + 3.0 * np.arange(6, dtype=np.float32)[None, :].repeat(6, 0)  # 3 footprints per pixel
    np.testing.assert_array_equal(flying_pixel_filter(slope, CAMERA, footprints=10.0), slope)


def _plane(h=40, w=50, z0=500.0, gu=0.4, gv=-0.25):
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    return z0 + gu * u + gv * v


def test_denoise_depth_keeps_a_plane_and_averages_its_noise():
    """A slanted plane (0.4 and 0.25 footprints per pixel) stays as it is; with 0.2 mm of noise the plane fit over
    a 9x9 window leaves about 0.2 / 9 (the corners see fewer pixels)."""
    plane = _plane()
    np.testing.assert_allclose(denoise_depth(plane.astype(np.float32), CAMERA, 4), plane, atol=2e-4)
    noisy = plane + np.random.default_rng(0).normal(0.0, 0.2, plane.shape)
    out = denoise_depth(noisy.astype(np.float32), CAMERA, 4)
    inner = (slice(4, -4), slice(4, -4))
    assert np.abs(out - plane)[inner].mean() < 0.2 * 0.8 / 9 * 1.5
    assert np.abs(out - plane).mean() < 0.5 * np.abs(noisy - plane).mean()


def test_denoise_depth_keeps_each_side_of_a_depth_edge_and_the_holes():
    """A 20 mm step (20 footprints) between two noisy planes: the pixels beside it are fitted on their own side
    only (a mixed fit would be mm off); NaN pixels stay NaN and take no part; radius 0 changes nothing."""
    rng = np.random.default_rng(1)
    truth = _plane()
    truth[:, 25:] += 20.0
    noisy = (truth + rng.normal(0.0, 0.1, truth.shape)).astype(np.float32)
    noisy[10:14, 5:9] = np.nan
    out = denoise_depth(noisy, CAMERA, 3, footprints=4.0)
    np.testing.assert_array_equal(np.isnan(out), np.isnan(noisy))
    ok = np.isfinite(out)
    assert np.abs(out - truth)[ok].max() < 0.3
    assert np.abs(out - truth)[:, 23:27].mean() < np.abs(noisy - truth)[:, 23:27].mean()
    np.testing.assert_array_equal(denoise_depth(noisy, CAMERA, 0), noisy)


def test_denoise_depth_bias_on_a_sphere_is_the_stated_one():
    """The cap of a sphere of radius 50 mm at 500 mm (1 mm footprints): the plane fit's bias at the apex is about
    mean(u^2 + v^2) / (2 R) over the window (denoise_depth's docstring): 0.04 mm for radius 2, with u, v in mm."""
    R, z0, r = 50.0, 500.0, 2
    v, u = np.mgrid[-20:21, -20:21].astype(np.float64)  # mm, as the footprint is 1 mm
    cap = z0 - np.sqrt(np.maximum(R * R - u * u - v * v, 0.0)) + R
    out = denoise_depth(cap.astype(np.float32), CAMERA, r, footprints=10.0)
    w = np.arange(-r, r + 1, dtype=np.float64)
    expected = 2 * np.mean(w * w) / (2 * R)
    assert abs((out[20, 20] - cap[20, 20]) - expected) < 0.1 * expected


def test_readmit_edge_pixels_gives_back_each_side_of_an_edge_but_not_what_lies_between():
    """A 100 mm step with one column in between: the filter drops the step's two sides and the middle column;
    the sides have 3 kept neighbours on their own surface and come back when their codes confirm them, the
    middle one has none. A confidence below the bar (0.9 by default), a support bar above 3, or a side bent 20 mm toward the other surface, keeps them out."""
    d = np.full((6, 8), 500.0, np.float32)
    d[:, 4] = 550.0  # between the surfaces: a mixed pixel
    d[:, 5:] = 600.0
    after = flying_pixel_filter(d, CAMERA, footprints=10.0)
    assert np.isnan(after[:, 3:6]).all() and np.isfinite(after[:, :3]).all() and np.isfinite(after[:, 6:]).all()
    seen = []

    def confident(m):
        seen.append(np.isfinite(m))
        return np.where(np.isfinite(m), 1.0, np.nan)

    back = readmit_edge_pixels(d, after, CAMERA, 10.0, confident, **BAR)
    expect = np.zeros(d.shape, bool)
    expect[1:-1, [3, 5]] = True  # on the image's border two kept neighbours are too few
    np.testing.assert_array_equal(back, expect)
    np.testing.assert_array_equal(seen[0], expect)  # confidence asked only at the candidates
    fair = lambda m: np.where(np.isfinite(m), 0.85, np.nan)  # noqa: E731  between the surface term's 0.8 and 0.9
    assert not readmit_edge_pixels(d, after, CAMERA, 10.0, fair, **BAR).any()
    np.testing.assert_array_equal(readmit_edge_pixels(d, after, CAMERA, 10.0, fair, **{**BAR, "min_confidence": 0.8}), expect)
    assert not readmit_edge_pixels(d, after, CAMERA, 10.0, confident, **{**BAR, "min_support": 4}).any()
    bent = d.copy()
    bent[:, 3] = 520.0  # the field's surface bending toward the background: 20 footprints from its neighbours
    back = readmit_edge_pixels(bent, flying_pixel_filter(bent, CAMERA, 10.0), CAMERA, 10.0, confident, **BAR)
    assert not back[:, 3].any() and back[1:-1, 5].all()
    # nothing dropped: nothing to give back, and no confidence asked
    seen.clear()
    assert not readmit_edge_pixels(d[:, :3], d[:, :3], CAMERA, 10.0, confident, **BAR).any() and not seen


def test_extract_mesh_leaves_out_the_volume_outside_the_depth_range():
    """A ball in the volume's margin before the near plane (where training never samples) is no surface; the
    plane inside the range stays whole, and the inside behind it is not capped at the far plane."""
    import torch

    from slwarp.neural.extraction.surface import extract_mesh
    from slwarp.neural.fields import Volume

    vol = Volume((-100.0, -100.0, 400.0), (100.0, 100.0, 1000.0))
    ball_centre = torch.tensor([0.0, 0.0, 420.0])

    def field(x):  # the plane z = 800 mm (positive on the camera's side) and a 30 mm ball at z = 420 mm
        return torch.minimum(800.0 - x[..., 2], torch.linalg.norm(x - ball_centre, dim=-1) - 30.0)

    full = extract_mesh(field, vol, 64)
    cropped = extract_mesh(field, vol, 64, depth_range=(450.0, 950.0))
    assert full.vertices[:, 2].min() < 450.0  # the ball
    np.testing.assert_allclose(cropped.vertices[:, 2], 800.0, atol=1e-3)
    assert len(cropped.faces) == np.sum(np.abs(full.triangles_center[:, 2] - 800.0) < 1.0)


def test_extract_depth_uniform_fill_only_adds_pixels_without_contrast(tiny_rods_field):
    """extract_depth with uniform_fill: the same field's depth map plus pixels outside the lit-with-contrast map
    (counted in timings["filled_uniform"], with a confidence), nothing else moved; none outside `region`. Without the
    stage nothing reports a fill."""
    from slwarp.neural.extraction import extract_depth

    _, cfg, trainer = tiny_rods_field
    trainer.cfg = cfg
    lit = trainer.renderer.valid_map.cpu().numpy()
    plain, _, _, t_plain, _ = extract_depth(trainer, lit)
    trainer.cfg = cfg.with_options(uniform_fill=True)
    filled, conf, _, t_fill, _ = extract_depth(trainer, lit)
    assert "filled_uniform" not in t_plain and "uniform_fill_s" not in t_plain
    had = np.isfinite(plain)
    np.testing.assert_array_equal(filled[had], plain[had])
    new = np.isfinite(filled) & ~had
    assert t_fill["filled_uniform"] == int(new.sum()) > 0
    assert not (new & lit).any()
    assert np.isfinite(conf[new]).all()
    none = extract_depth(trainer, lit, region=np.zeros_like(lit))[0]
    np.testing.assert_array_equal(np.isfinite(none), had)


def test_extract_depth_denoises_last_without_adding_or_losing_pixels(tiny_rods_field):
    """extract_depth with denoise_radius: the same pixels have depth, their depths are denoise_depth's of the map
    without it, and the stage's time is reported."""
    from slwarp.neural.extraction import extract_depth

    scan, cfg, trainer = tiny_rods_field
    trainer.cfg = cfg
    lit = trainer.renderer.valid_map.cpu().numpy()
    plain = extract_depth(trainer, lit).depth
    trainer.cfg = cfg.with_options(denoise_radius=3, denoise_footprints=4.0)
    got = extract_depth(trainer, lit)
    np.testing.assert_array_equal(np.isfinite(got.depth), np.isfinite(plain))
    np.testing.assert_allclose(got.depth, denoise_depth(plain, scan.camera, 3, 4.0), rtol=0, atol=1e-4)
    assert not np.array_equal(got.depth, plain) and got.timings["denoise_s"] >= 0.0


def test_extract_depth_refine_check_reports_and_follows_its_decision(tiny_rods_field, monkeypatch):
    """With refine_range > 0, extract_depth reports the held-out check in timings["refine_check"]; a refused
    refinement leaves the depth as it was before refinement, a kept one (or refine_check off) gives the refined map."""
    import slwarp.neural.extraction as rc
    import slwarp.neural.extraction.stages as stages

    _, cfg, trainer = tiny_rods_field
    lit = trainer.renderer.valid_map.cpu().numpy()
    trainer.cfg = cfg.with_options(refine_range=0.0)
    plain = rc.extract_depth(trainer, lit)[0]
    trainer.cfg = cfg.with_options(refine_range=1.0, refine_check=False)
    refined, _, _, t_off, _ = rc.extract_depth(trainer, lit)
    assert t_off["refine_check"] is None
    assert not np.array_equal(refined[np.isfinite(refined)], plain[np.isfinite(plain)])
    trainer.cfg = cfg.with_options(refine_range=1.0, refine_check=True)
    _, _, _, t_on, _ = rc.extract_depth(trainer, lit)
    check = t_on["refine_check"]
    assert set(check) == {"keep", "before", "after"} and len(check["before"]) == trainer.n_frames
    for keep, want in ((False, plain), (True, refined)):
        monkeypatch.setattr(stages, "refinement_generalises",
                            lambda *a, keep=keep, **k: {"keep": keep, "before": [0.1], "after": [0.2 if not keep else 0.05]})
        got = rc.extract_depth(trainer, lit)[0]
        np.testing.assert_array_equal(got, want)
    trainer.cfg = cfg


def test_extract_depth_skips_the_refinement_through_a_lens_halo_unless_asked(tiny_rods_field):
    """refine_through_halo false: where the trainer's patterns carry a lens halo (halo_share > 0, a real lens) the
    refinement is skipped and says why; without a halo, or with refine_through_halo, it refines as before."""
    import slwarp.neural.extraction as rc

    _, cfg, trainer = tiny_rods_field
    lit = trainer.renderer.valid_map.cpu().numpy()
    trainer.cfg = cfg.with_options(refine_range=0.0)
    plain = rc.extract_depth(trainer, lit)[0]
    trainer.cfg = cfg.with_options(refine_range=1.0)
    refined = rc.extract_depth(trainer, lit)[0]
    try:
        for share, through, want, skipped in ((0.0, False, refined, None), (0.1, False, plain, "lens halo"),
                                              (0.1, True, refined, None)):
            trainer.halo_share = share
            trainer.cfg = cfg.with_options(refine_range=1.0, refine_through_halo=through)
            depth, _, _, t, _ = rc.extract_depth(trainer, lit)
            np.testing.assert_array_equal(depth, want)
            assert t.get("refine_skipped") == skipped and t["refined"] == (skipped is None)
    finally:
        trainer.halo_share = 0.0
        trainer.cfg = cfg


def test_extract_depth_fate_says_what_became_of_each_pixel(tiny_rods_field):
    """Extraction.fate: a pixel has depth exactly when its fate is measured, repaired or filled; no contrast outside
    the lit-with-contrast map (unless filled); each filter's fate at no more pixels than it dropped (the repair may
    give some back), and exactly as many without the repair; repaired and filled as their stages count them."""
    from slwarp.neural.extraction import FATE, PIXEL_FATES, extract_depth, fate_counts

    _, cfg, trainer = tiny_rods_field
    lit = trainer.renderer.valid_map.cpu().numpy()
    stages = ("no_surface", "out_of_range", "flying_pixel", "low_confidence", "search_doubt")
    try:
        for repair in (False, True):
            trainer.cfg = cfg.with_options(search_repair=repair, search_doubt=True, uniform_fill=True, refine_range=0.0)
            ext = extract_depth(trainer, lit)
            fate, depth, t = ext.fate, ext.depth, ext.timings
            assert fate.shape == depth.shape and fate.dtype == np.uint8 and int(fate.max()) < len(PIXEL_FATES)
            with_depth = np.isin(fate, [FATE["measured"], FATE["repaired"], FATE["filled"]])
            np.testing.assert_array_equal(with_depth, np.isfinite(depth))
            np.testing.assert_array_equal(fate == FATE["no_contrast"], ~lit & (fate != FATE["filled"]))
            counts = fate_counts(fate)
            assert sum(counts.values()) == depth.size
            assert counts["filled"] == t["filled_uniform"] > 0
            assert counts["low_confidence"] + counts["flying_pixel"] > 0  # the tiny field's map has both
            for stage in stages:
                if repair:
                    assert counts[stage] <= t["dropped"].get(stage, 0), stage
                else:
                    assert counts[stage] == t["dropped"].get(stage, 0), stage
            assert counts["repaired"] == (t["repair"]["kept"] if repair else 0)
    finally:
        trainer.cfg = cfg


def test_save_fate_map_writes_a_picture_and_refuses_an_unnamed_fate(tmp_path):
    import cv2
    import pytest

    from slwarp.evaluation.viz import save_fate_map
    from slwarp.neural.extraction import PIXEL_FATES

    fate = np.arange(len(PIXEL_FATES), dtype=np.uint8).repeat(40).reshape(len(PIXEL_FATES) * 4, 10)
    save_fate_map(tmp_path / "f.png", fate, PIXEL_FATES)
    img = cv2.imread(str(tmp_path / "f.png"))
    assert img is not None and img.shape[0] > 50 and img.std() > 10
    with pytest.raises(ValueError, match="fate value 9 has no name"):
        save_fate_map(tmp_path / "g.png", np.full((4, 4), 9, np.uint8), PIXEL_FATES)


def test_extract_depth_skips_the_refinement_where_the_model_misfits(tiny_rods_field):
    """refine_max_misfit: above the measured misfit the depth is refined as without a limit, below it the
    refinement is skipped (the depth as with refine_range 0); timings report the misfit and the decision (nothing
    without the refinement)."""
    from slwarp.neural.extraction import extract_depth

    _, cfg, trainer = tiny_rods_field
    lit = trainer.renderer.valid_map.cpu().numpy()
    try:
        trainer.cfg = cfg.with_options(refine_range=0.0)
        plain = extract_depth(trainer, lit)
        trainer.cfg = cfg.with_options(refine_range=1.0)
        refined = extract_depth(trainer, lit)
        assert refined.timings["refine_misfit"] is None and refined.timings["refined"]
        assert "refine_misfit" not in plain.timings and "refined" not in plain.timings
        for limit, want, done in ((1.0, refined.depth, True), (1e-4, plain.depth, False)):
            trainer.cfg = cfg.with_options(refine_range=1.0, refine_max_misfit=limit)
            got = extract_depth(trainer, lit)
            assert 1e-4 < got.timings["refine_misfit"] < 1.0
            assert got.timings["refined"] is done
            np.testing.assert_array_equal(got.depth, want)
    finally:
        trainer.cfg = cfg


def _ball_grid(n: int = 49):
    """A 40 mm ball's SDF (mm) on an n^3 grid over a 120 mm cube at z 400-520 mm: (values, origin, spacing)."""
    h = 120.0 / (n - 1)
    origin = np.array([-60.0, -60.0, 400.0])
    x, y, z = np.meshgrid(*[origin[i] + h * np.arange(n) for i in range(3)], indexing="ij")
    return (np.sqrt(x**2 + y**2 + (z - 460.0) ** 2) - 40.0).astype(np.float32), origin, h


def test_extract_mesh_winds_faces_and_normals_outward():
    """The mesh's faces are wound towards positive SDF (a positive volume) and its vertex normals agree."""
    import torch

    from slwarp.neural.extraction.surface import extract_mesh
    from slwarp.neural.fields import Volume

    centre = torch.tensor([0.0, 0.0, 460.0])
    mesh = extract_mesh(lambda x: torch.linalg.norm(x - centre, dim=-1) - 40.0,
                        Volume((-60.0, -60.0, 400.0), (60.0, 60.0, 520.0)), 48)
    assert abs(mesh.volume - 4.0 / 3.0 * np.pi * 40.0**3) < 0.02 * mesh.volume  # > 0: outward
    radial = mesh.vertices - centre.numpy()
    assert (np.einsum("ij,ij->i", mesh.vertex_normals, radial) > 0).all()


def test_warp_marching_cubes_matches_scikit_image():
    """The GPU path's marching cubes (Warp's, run here on the CPU) and scikit-image's: vertices on the ball
    alike, the same volume, outward winding, and the same depth map by ray casting (to within a few % of a cell)."""
    import torch
    import trimesh
    from skimage.measure import marching_cubes

    from slwarp.neural.extraction.surface import _marching_cubes_warp, mesh_depth
    from slwarp.scans.scanner import Camera

    values, origin, h = _ball_grid()
    verts, faces = _marching_cubes_warp(torch.from_numpy(values), origin, h)
    v2, f2, _, _ = marching_cubes(values, level=0.0, spacing=(h, h, h))
    ours, theirs = trimesh.Trimesh(verts, faces, process=False), trimesh.Trimesh(v2 + origin, f2, process=False)
    radius = np.linalg.norm(verts - [0.0, 0.0, 460.0], axis=1)
    assert np.abs(radius - 40.0).max() < 0.1 * h
    assert ours.volume > 0 and abs(ours.volume - theirs.volume) < 1e-3 * theirs.volume
    cam = Camera(64, 64, [[400.0, 0.0, 31.5], [0.0, 400.0, 31.5], [0.0, 0.0, 1.0]])
    d1, d2 = mesh_depth(ours, cam, "cpu"), mesh_depth(theirs, cam, "cpu")
    hit = np.isfinite(d2)
    assert hit.sum() > 1000 and np.array_equal(hit, np.isfinite(d1))
    diff = np.abs(d1[hit] - d2[hit])
    # the cells' triangulations may differ (the surface inside a cell is not planar): by a few % of a cell at most
    assert np.median(diff) < 1e-4 and diff.max() < 0.02 * h


def test_depth_to_points_puts_each_finite_pixel_on_its_ray_at_its_depth():
    from slwarp.neural.depth_maps import depth_to_points
    from slwarp.scans.scanner import camera_rays
    from slwarp.sim.rigs import make_rig

    cam, _ = make_rig("small")
    rng = np.random.default_rng(0)
    depth = rng.uniform(600, 900, (cam.height, cam.width)).astype(np.float32)
    depth[rng.uniform(size=depth.shape) < 0.3] = np.nan
    pts = depth_to_points(depth, cam)
    ok = np.isfinite(depth)
    assert pts.shape == (ok.sum(), 3) and pts.dtype == np.float32
    np.testing.assert_allclose(pts[:, 2], depth[ok], rtol=1e-6)
    rays = camera_rays(cam)[ok]
    np.testing.assert_allclose(pts[:, :2], rays[:, :2] / rays[:, 2:3] * depth[ok][:, None], rtol=1e-5, atol=1e-3)
