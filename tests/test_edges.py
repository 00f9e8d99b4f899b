"""The edge sides at extraction (slwarp.neural.extraction.edges.settle_edge_sides): a band of pixels that kept the
other surface's depth beside a depth edge is given back its own surface, and the right pixels of an edge stay; the
stage in a preset's list (extraction.stages.EdgeSide) through its switch, edge_side_radius."""
import numpy as np
import pytest
import torch

from slwarp.neural.config import preset
from slwarp.neural.depth_maps import neighbour_stack
from slwarp.neural.extraction.edges import settle_edge_sides
from slwarp.neural.extraction.state import ModelInputs
from slwarp.neural.pattern_model import blur_patterns, lit_with_contrast, offset_and_modulation, photometric_residual
from slwarp.sim.simulate import SimOptions, simulate_scene

BLUR = 1.0  # projector px: the simulated defocus, and the blur the patterns are rendered with
FOOTPRINTS = 10.0


@pytest.fixture(scope="module")
def steps():
    """(scan, rendered patterns, valid pixels, the right depth map) of the small-rig steps scene: a depth-independent
    projector blur, no noise, flat albedo. Simulated on a GPU where there is one (the machines with one may lack
    Warp's CPU compiler)."""
    opts = SimOptions(noise=False, bits=0, defocus_sigma=BLUR, defocus_slope=0.0, shading=False, texture=False)
    scan = simulate_scene("steps", "random6", rig="small", options=opts,
                          device="cuda:0" if torch.cuda.is_available() else "cpu")
    patterns = blur_patterns(torch.as_tensor(scan.patterns), BLUR).numpy()
    valid = lit_with_contrast(offset_and_modulation(scan.images)[1]) & np.isfinite(scan.gt_depth)
    return scan, patterns, valid, np.where(valid, scan.gt_depth, np.nan).astype(np.float32)


def _inputs(scan, patterns, valid, device="cpu") -> ModelInputs:
    if device != "cpu":  # the extraction on a GPU: the model's arrays as tensors there
        images = torch.as_tensor(scan.images, device=device)
        patterns = torch.as_tensor(patterns, device=device)
        return ModelInputs(scan.camera, scan.projector, images, patterns, scan.depth_range, valid=valid, device=device,
                           host_images=scan.images)
    return ModelInputs(scan.camera, scan.projector, scan.images, patterns, scan.depth_range, valid=valid)


def _far_band(gt, camera):
    """[H, W] bool: the pixels on the far side of a depth edge, and [H, W] the nearest depth across it."""
    limit = FOOTPRINTS * gt / min(camera.fx, camera.fy)
    near = neighbour_stack(gt)
    with np.errstate(invalid="ignore"):
        nearer = near < gt - limit[None]
    return nearer.any(0), np.min(np.where(nearer, near, np.inf), axis=0)


def test_a_band_with_the_foregrounds_depth_takes_its_own_back(steps, device):
    scan, patterns, valid, gt = steps
    band, fore = _far_band(gt, scan.camera)
    assert band.sum() > 500
    depth = gt.copy()
    depth[band] = fore[band]  # the field drew each step's edge a pixel too far out
    out, switched, dropped = settle_edge_sides(depth, _inputs(scan, patterns, valid, device), 1, 0.5, FOOTPRINTS)
    right = np.abs(out - gt) < 2.0
    assert (band & right).sum() > 0.8 * band.sum()
    assert (band & np.isfinite(out) & ~right).sum() < 0.1 * band.sum()  # few stay wrong; the rest are dropped
    others = np.isfinite(depth) & ~band
    assert not (switched & others).any() and (dropped & others).sum() < 0.05 * band.sum()
    np.testing.assert_array_equal(out[~(switched | dropped)], depth[~(switched | dropped)])
    assert not np.isfinite(out[dropped]).any() and np.isfinite(out[switched]).all()


def _settle_with_maps(depth, inputs, radius, margin, footprints):
    """The edge sides as first written (the reference): a residual map per window offset
    (pattern_model.photometric_residual), the lowest kept by a strict comparison, offset after offset."""
    d = np.asarray(depth, np.float32)
    H, W = d.shape
    limit = footprints * d / min(inputs.camera.fx, inputs.camera.fy)
    pad = np.pad(d, radius, constant_values=np.nan)
    edge = np.zeros(d.shape, bool)
    best = np.full(d.shape, np.inf, np.float32)
    best_depth = np.full(d.shape, np.nan, np.float32)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            if (dy, dx) == (0, 0):
                continue
            n = pad[radius + dy : radius + dy + H, radius + dx : radius + dx + W]
            with np.errstate(invalid="ignore"):
                candidate = np.where(np.abs(n - d) > limit, n, np.nan).astype(np.float32)
            edge |= np.isfinite(candidate)
            r = np.nan_to_num(photometric_residual(candidate, *inputs.model), nan=np.inf)
            lower = r < best
            best, best_depth = np.where(lower, r, best), np.where(lower, candidate, best_depth)
    r_own = np.nan_to_num(photometric_residual(np.where(edge, d, np.nan).astype(np.float32), *inputs.model), nan=np.inf)
    switched = edge & np.isfinite(best) & (best <= margin * r_own)
    dropped = edge & ~switched & ~(r_own <= margin * best)
    out = d.copy()
    out[switched] = best_depth[switched]
    out[dropped] = np.nan
    return out, switched, dropped


def test_the_pairs_in_one_call_settle_as_a_residual_map_per_offset_did(steps, device):
    """settle_edge_sides evaluates every (pixel, depth across) pair in one call where the model's patterns are; it
    settles each pixel exactly as the per-offset residual maps did (holes in the map, radius 1 and 2)."""
    scan, patterns, valid, gt = steps
    band, fore = _far_band(gt, scan.camera)
    depth = gt.copy()
    depth[band] = fore[band]
    depth[::7, ::5] = np.nan
    inputs = _inputs(scan, patterns, valid, device)
    for radius in (1, 2):
        got = settle_edge_sides(depth, inputs, radius, 0.5, FOOTPRINTS)
        want = _settle_with_maps(depth, inputs, radius, 0.5, FOOTPRINTS)
        assert want[1].sum() > 100 and want[2].sum() > 10
        for g, w in zip(got, want):
            np.testing.assert_array_equal(g, w)


def test_the_right_map_keeps_its_edges_and_radius_0_changes_nothing(steps):
    scan, patterns, valid, gt = steps
    inputs = _inputs(scan, patterns, valid)
    limit = FOOTPRINTS * gt / min(scan.camera.fx, scan.camera.fy)
    edge = np.isfinite(gt) & (np.abs(np.nan_to_num(neighbour_stack(gt) - gt, nan=0.0)) > limit).any(0)
    out, switched, dropped = settle_edge_sides(gt, inputs, 1, 0.5, FOOTPRINTS)
    assert edge.sum() > 1000 and not switched.any() and dropped.sum() < 0.08 * edge.sum() and not (dropped & ~edge).any()
    same, none, nothing = settle_edge_sides(gt, inputs, 0, 0.5, FOOTPRINTS)
    np.testing.assert_array_equal(same, gt)
    assert not none.any() and not nothing.any()


def test_edge_side_radius_switches_the_stage_in_before_the_denoising():
    on = preset("tuned", edge_side_radius=2)
    stages = list(on.extraction.stages)
    assert stages.index("repair_grow") < stages.index("edge_side") == stages.index("denoise") - 1
    assert "edge_side" not in preset("tuned").extraction.stages
    assert on.with_options(edge_side_radius=0).extraction.stages == preset("tuned").extraction.stages
    for name in ("fast", "accurate", "cpu-hashgrid"):  # the hash-grid presets have it
        assert preset(name).extraction.stages == preset(name, edge_side_radius=2).extraction.stages


def test_extract_depth_with_the_edge_sides_records_their_fates_and_counts(tiny_rods_field):
    """In the extraction (a tiny field on the small-rig rods, with the search repair, which gives the rods back
    beside the background: edges the stage settles), the stage's drops get the fate "edge_side" and their count, its
    switches the fate "repaired"; the pixels it leaves alone are as without it."""
    from slwarp.neural.extraction import FATE, extract_depth, pixel_fates

    _, cfg, trainer = tiny_rods_field
    lit = trainer.renderer.valid_map.cpu().numpy()
    try:
        trainer.cfg = cfg.with_options(search_repair=True)
        plain = extract_depth(trainer, lit)
        trainer.cfg = cfg.with_options(search_repair=True, edge_side_radius=1)
        got = extract_depth(trainer, lit)
    finally:
        trainer.cfg = cfg
    counts = got.timings["edge_side"]
    dropped = got.fate == pixel_fates().index("edge_side")
    assert counts["switched"] > 100 and counts["dropped"] > 100
    assert counts["dropped"] == int(dropped.sum()) == got.timings["dropped"].get("edge_side", 0)
    assert np.isnan(got.depth[dropped]).all() and np.isfinite(plain.depth[dropped]).all()
    moved = np.isfinite(got.depth) & (got.depth != plain.depth)
    assert moved.sum() == counts["switched"] and (got.fate[moved] == FATE["repaired"]).all()
    same = ~dropped & ~moved
    np.testing.assert_array_equal(got.depth[same], plain.depth[same])


def test_the_repairs_searches_take_the_sets_window_step(steps, monkeypatch):
    """ModelInputs.window_step (a set designed for spaced windows) reaches every depth search of the search repair
    and of its doubt rule; with the true depths the step-1 and step-3 doubts both keep nearly every pixel."""
    from dataclasses import replace

    from slwarp.neural.extraction import repair

    scan, patterns, valid, gt = steps
    seen, real = [], repair.search_depth

    def spy(*args, **kwargs):
        seen.append(kwargs.get("window_step"))
        return real(*args, **kwargs)

    monkeypatch.setattr(repair, "search_depth", spy)
    band = np.zeros_like(valid)
    band[valid.shape[0] // 2 - 16: valid.shape[0] // 2 + 16] = True  # the searches over a band of rows: quicker
    valid = valid & band
    inputs = _inputs(scan, patterns, valid)
    assert inputs.window_step == 1
    for step in (1, 3):
        seen.clear()
        out, info = repair.doubt_by_search(gt, replace(inputs, window_step=step))
        assert seen == [step] and info["dropped"] < 0.01 * valid.sum()
        seen.clear()
        repair.repair_by_search(np.where(np.arange(gt.shape[1]) % 7 == 0, np.nan, gt), replace(inputs, window_step=step),
                                min_confidence=0.6)
        assert seen and set(seen) == {step}
