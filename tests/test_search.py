"""The depth search (slwarp.neural.start.search): the search along each ray, its `centres` option, and the search repair
at extraction (slwarp.neural.extraction.repair: repair_by_search fills holes, replaces contradicted depths and
refuses isolated changes; doubt_by_search, its doubt rule alone, drops contradicted depths the codes do not support;
grow_repair spreads the repair's changes)."""
import warnings

import numpy as np
import pytest
import torch

from slwarp.neural.depth_maps import component_sizes, neighbour_stack, neighbours_within
from slwarp.neural.extraction.repair import doubt_by_search, grow_repair, repair_by_search
from slwarp.neural.extraction.state import ModelInputs
from slwarp.neural.pattern_model import blur_patterns, lit_with_contrast, offset_and_modulation
from slwarp.neural.start.search import search_depth
from slwarp.sim.simulate import SimOptions, simulate_scene

BLUR = 1.0  # projector px: the simulated defocus, and the blur the patterns are rendered with


@pytest.fixture(scope="module")
def scene():
    """(scan, rendered patterns, valid pixels) of the small-rig steps scene: a depth-independent projector blur,
    no noise, flat albedo."""
    opts = SimOptions(noise=False, bits=0, defocus_sigma=BLUR, defocus_slope=0.0, shading=False, texture=False)
    scan = simulate_scene("steps", "random6", rig="small", options=opts, device="cpu")
    patterns = blur_patterns(torch.as_tensor(scan.patterns), BLUR).numpy()
    _, b = offset_and_modulation(scan.images)
    valid = lit_with_contrast(b) & np.isfinite(scan.gt_depth)
    return scan, patterns, valid



def _inputs(scan, patterns, valid=None, **kw) -> ModelInputs:
    """The pattern model's inputs of a simulated scan, as the extraction bundles them (searches every 1 mm on the
    CPU unless kw says otherwise)."""
    return ModelInputs(scan.camera, scan.projector, scan.images, patterns, kw.pop("depth_range", scan.depth_range),
                       valid=valid, **{"step_mm": 1.0, "device": "cpu", **kw})

def _search(scan, patterns, valid, **kw):
    return search_depth(scan.camera, scan.projector, scan.images, patterns, scan.depth_range, valid=valid, device="cpu",
                        **kw)[0]


def test_search_finds_the_depth_of_most_pixels(scene):
    scan, patterns, valid = scene
    depth = _search(scan, patterns, valid, radius=2, stride=1, step_mm=1.0)
    found = np.isfinite(depth)
    assert found[valid].mean() > 0.8
    err = np.abs(depth - scan.gt_depth)[found]
    assert np.mean(err < 2.0) > 0.95  # hypotheses 1 mm apart; the rest sit on depth edges


def test_search_centres_limit_where_it_searches_but_not_the_windows(scene):
    scan, patterns, valid = scene
    centres = np.zeros_like(valid)
    centres[100:140, 150:200] = True
    full = _search(scan, patterns, valid, radius=1, stride=1, median=False)
    part = _search(scan, patterns, valid, radius=1, stride=1, median=False, centres=centres)
    inside = centres & valid
    assert inside.sum() > 1000
    np.testing.assert_array_equal(part[inside], full[inside])
    assert np.isnan(part[~inside]).all()


def test_repair_fills_holes_and_replaces_contradicted_depths(scene):
    scan, patterns, valid = scene
    gt = np.where(valid, scan.gt_depth, np.nan).astype(np.float32)
    depth = gt.copy()
    # two 30 x 30 blocks of lit pixels on one surface each (no depth edge inside)
    blocks = [(y, x) for y in range(10, 220, 15) for x in range(10, 290, 15)
              if valid[y : y + 30, x : x + 30].all()
              and np.ptp(scan.gt_depth[y : y + 30, x : x + 30]) < 15.0]
    y0, x0 = blocks[0]
    y1, x1 = next(b for b in blocks if abs(b[0] - y0) >= 30 or abs(b[1] - x0) >= 30)  # not overlapping
    hole = np.zeros_like(valid)
    hole[y0 : y0 + 30, x0 : x0 + 30] = True
    wrong = np.zeros_like(valid)
    wrong[y1 : y1 + 30, x1 : x1 + 30] = True
    depth[hole] = np.nan
    depth[wrong] += 40.0  # a surface 40 mm behind the true one: another code, the field's kind of mistake
    out, info = repair_by_search(depth, _inputs(scan, patterns, valid), min_confidence=0.6)
    assert info["filled"] > 0 and info["switched"] > 0
    assert np.mean(np.abs(out[hole] - gt[hole]) < 2.0) > 0.8
    assert np.mean(np.abs(out[wrong] - gt[wrong]) < 2.0) > 0.8
    # the right depths elsewhere stay as they were (a rare confident wrong search may not overrule them)
    rest = valid & ~hole & ~wrong
    assert np.mean(out[rest] != depth[rest]) < 0.005
    # nothing changes outside `valid`
    assert np.isnan(out[~valid]).all()


def test_search_and_repair_take_tensors_as_the_extraction_on_a_gpu_passes_them(scene):
    """The frames as tensors (the GPU extraction passes the renderer's; here on the CPU): the search's map is the
    same as from numpy bit for bit, and the repair, whose confidences torch then computes, decides the same. (A
    depth range around the scene's, 2 mm hypotheses and the top 160 rows: equality needs no fine search, and CI's
    time is short.)"""
    scan, patterns, valid = scene
    valid = valid.copy()
    valid[160:] = False
    images_t, patterns_t = torch.as_tensor(scan.images), torch.as_tensor(patterns)
    gt = scan.gt_depth[valid]
    depth_range = (float(gt.min()) - 60.0, float(gt.max()) + 60.0)
    for kw in (dict(radius=1, stride=1), dict(radius=2, stride=2)):
        host = search_depth(scan.camera, scan.projector, scan.images, patterns, depth_range, valid=valid,
                            device="cpu", step_mm=2.0, **kw)[0]
        got = search_depth(scan.camera, scan.projector, images_t, patterns_t, depth_range, valid=valid,
                           device="cpu", step_mm=2.0, **kw)[0]
        assert np.isfinite(host).sum() > 0.5 * valid.sum()
        np.testing.assert_array_equal(got, host)
    depth = np.where(valid, scan.gt_depth, np.nan).astype(np.float32)
    depth[40:70, 60:90] += 40.0
    depth[120:150, 150:180] = np.nan
    common = dict(depth_range=depth_range, valid=valid, step_mm=2.0)
    out_host, info_host = repair_by_search(depth, _inputs(scan, patterns, **common), min_confidence=0.6)
    out_t, info_t = repair_by_search(depth, ModelInputs(scan.camera, scan.projector, images_t, patterns_t, **common),
                                     min_confidence=0.6)
    assert info_t == info_host and info_host["switched"] > 0 and info_host["filled"] > 0
    np.testing.assert_array_equal(out_t, out_host)


def test_repair_keeps_only_large_groups_of_changes_when_asked(scene):
    scan, patterns, valid = scene
    gt = np.where(valid, scan.gt_depth, np.nan).astype(np.float32)
    depth = gt.copy()
    blocks = [(y, x) for y in range(10, 220, 15) for x in range(10, 290, 15)
              if valid[y : y + 30, x : x + 30].all() and np.ptp(scan.gt_depth[y : y + 30, x : x + 30]) < 15.0]
    y0, x0 = blocks[0]
    y1, x1 = next(b for b in blocks if abs(b[0] - y0) >= 30 or abs(b[1] - x0) >= 30)
    hole, wrong = np.zeros_like(valid), np.zeros_like(valid)
    hole[y0 : y0 + 30, x0 : x0 + 30] = True
    wrong[y1 : y1 + 30, x1 : x1 + 30] = True
    depth[hole] = np.nan
    depth[wrong] += 40.0
    inputs = _inputs(scan, patterns, valid)
    out_big, info_big = repair_by_search(depth, inputs, min_confidence=0.6, min_component=300)
    out_none, info_none = repair_by_search(depth, inputs, min_confidence=0.6, min_component=2000)
    # a 300-pixel minimum keeps most of each 900-pixel block's change (one group each, right within 2 mm)
    assert np.sum(hole & (np.abs(out_big - gt) < 2.0)) > 600 and np.sum(wrong & (np.abs(out_big - gt) < 2.0)) > 600
    # a 2000-pixel minimum refuses every change: the hole stays empty, and the wrong depths whose codes fit the
    # search's clearly better are dropped rather than kept (measured: a few pixels stay, at the wrong depth)
    assert info_none["filled"] == info_none["switched"] == 0 and np.isnan(out_none[hole]).all()
    assert np.isnan(out_none[wrong]).mean() > 0.9
    kept = wrong & np.isfinite(out_none)
    np.testing.assert_array_equal(out_none[kept], depth[kept])


def test_the_repair_group_size_counts_pixels_as_on_a_full_size_camera(scene):
    """repair_min_component is a count on a 1280 x 1024 camera: a quarter-size image (the small rigs) asks 1/16 of it
    but at least 10 (or what was given, when less), a full-size or larger one all of it; the search repair stage
    repairs with the scaled size and reports it."""
    from slwarp.neural.extraction.repair import scaled_min_component
    from slwarp.neural.extraction.stages import SearchRepair
    from slwarp.neural.extraction.state import State

    assert scaled_min_component(100, (1024, 1280)) == 100 and scaled_min_component(100, (2048, 2560)) == 100
    assert scaled_min_component(100, (256, 320)) == 10 and scaled_min_component(320, (256, 320)) == 20
    assert scaled_min_component(0, (256, 320)) == 0 and scaled_min_component(3, (8, 8)) == 3
    scan, patterns, valid = scene
    assert valid.shape == (256, 320)
    depth = np.where(valid, scan.gt_depth, np.nan).astype(np.float32)
    depth[40:70, 60:90] += 40.0
    inputs = _inputs(scan, patterns, valid)
    state = State(inputs=inputs, field=None, fate=np.zeros(valid.shape, np.uint8), timings={}, depth=depth)
    out = SearchRepair(min_confidence=0.6, repair_min_component=4800, doubt_confidence=0.7)(state)
    want, _ = repair_by_search(depth, inputs, min_confidence=0.6, min_component=300, doubt_confidence=0.7)
    assert out.info["repair"]["min_component"] == 300
    np.testing.assert_array_equal(out.depth, want)
    refused, _ = repair_by_search(depth, inputs, min_confidence=0.6, min_component=4800, doubt_confidence=0.7)
    assert not np.array_equal(np.isfinite(refused), np.isfinite(want))  # the unscaled size would refuse the block


def test_neighbours_within_at_listed_pixels_equals_the_dense_count():
    """neighbours_within(..., index) counts at the listed pixels what the dense map counts there, borders and NaN
    neighbours included (the uniform-code fill asks it at its fills only)."""
    rng = np.random.default_rng(3)
    depth = (500.0 + np.cumsum(rng.normal(0, 1.0, (40, 50)), axis=1)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.2] = np.nan
    index = np.concatenate([np.arange(50), rng.choice(depth.size, 300, replace=False), [depth.size - 1]])
    dense = neighbours_within(depth, 1.5)
    np.testing.assert_array_equal(neighbours_within(depth, 1.5, index), dense.reshape(-1)[index])
    assert 0 < dense.mean() < 8  # neither every neighbour nor none agrees


def test_component_sizes_link_neighbours_of_one_surface():
    d = np.full((6, 8), np.nan)
    d[0, 0:3] = 5.0
    d[1, 3] = 5.5  # a diagonal neighbour within 3 mm: the same group
    d[2, 0] = 50.0  # next to the group but 45 mm away: its own
    d[3:5, 0:2] = 100.0
    d[5, 7] = 1.0
    sizes = component_sizes(d, 3.0)
    expected = np.zeros((6, 8), int)
    expected[0, 0:3] = expected[1, 3] = 4
    expected[2, 0] = expected[5, 7] = 1
    expected[3:5, 0:2] = 4
    np.testing.assert_array_equal(sizes, expected)
    # a long diagonal band, one surface: one group, whatever the order of the unions
    band = np.where(np.abs(np.subtract.outer(np.arange(60), np.arange(60))) < 2, 700.0, np.nan)
    assert set(np.unique(component_sizes(band, 3.0))) == {0, int(np.isfinite(band).sum())}
    # a random map of three depths and holes: the group sizes of a plain flood fill
    rng = np.random.default_rng(1)
    d = np.where(rng.random((40, 50)) < 0.6, 10.0 * rng.integers(0, 3, (40, 50)), np.nan)
    np.testing.assert_array_equal(component_sizes(d, 3.0), _flood_fill_sizes(d, 3.0))
    # crossing diagonals: each links its own pair, never the other's
    cross = np.array([[0.0, 50.0], [50.0, 0.0]])
    np.testing.assert_array_equal(component_sizes(cross, 3.0), np.full((2, 2), 2))
    np.testing.assert_array_equal(component_sizes(np.array([[0.0, 50.0], [50.0, 100.0]]), 3.0), [[1, 2], [2, 1]])
    # one row, one column, all NaN, and random maps where many groups touch only through diagonals
    for shape in ((1, 30), (30, 1), (1, 1), (17, 23)):
        r = np.where(rng.random(shape) < 0.7, 10.0 * rng.integers(0, 2, shape), np.nan)
        np.testing.assert_array_equal(component_sizes(r, 3.0), _flood_fill_sizes(r, 3.0))
    np.testing.assert_array_equal(component_sizes(np.full((4, 5), np.nan), 3.0), np.zeros((4, 5)))
    checker = np.where((np.add.outer(np.arange(20), np.arange(20)) % 2) == 0, 5.0, 40.0)  # diagonal chains only
    np.testing.assert_array_equal(component_sizes(checker, 3.0), _flood_fill_sizes(checker, 3.0))


def test_median3_is_nanmedians_outlier_rule():
    """search._median3 drops what np.nanmedian's 3x3 median (NaN ignored, the two middle values averaged when
    their count is even) puts more than 10 mm away, on maps with every count of finite neighbours."""
    from slwarp.neural.start.search import _median3

    rng = np.random.default_rng(3)
    for share in (0.0, 0.2, 0.5, 0.9, 1.0):
        x = (500 + 12 * rng.standard_normal((31, 45))).astype(np.float32)
        x[rng.random(x.shape) > share] = np.nan
        stack = np.concatenate([neighbour_stack(x), x[None]]).astype(x.dtype)  # the 3x3 neighbourhood
        with np.errstate(invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN neighbourhoods
            med = np.nanmedian(stack, axis=0)
            expected = np.where(np.abs(x - med) < 10.0, x, np.nan)
        np.testing.assert_array_equal(_median3(x), expected)
    two = np.full((3, 3), np.nan, np.float32)
    two[1, 1], two[1, 2] = 0.0, 30.0  # each has one neighbour: the median of two is 15, 15 mm from both
    assert np.isnan(_median3(two)).all()


def _flood_fill_sizes(d, tol):
    """The group size of every finite pixel by a flood fill over the 8 neighbours within tol (reference)."""
    H, W = d.shape
    sizes = np.zeros((H, W), int)
    seen = ~np.isfinite(d)
    for y0, x0 in zip(*np.nonzero(~seen)):
        if seen[y0, x0]:
            continue
        seen[y0, x0] = True
        stack, members = [(y0, x0)], []
        while stack:
            y, x = stack.pop()
            members.append((y, x))
            for yy in range(max(0, y - 1), min(H, y + 2)):
                for xx in range(max(0, x - 1), min(W, x + 2)):
                    if not seen[yy, xx] and abs(d[yy, xx] - d[y, x]) < tol:
                        seen[yy, xx] = True
                        stack.append((yy, xx))
        for y, x in members:
            sizes[y, x] = len(members)
    return sizes


def test_repair_changes_nothing_on_a_right_depth_map(scene):
    scan, patterns, valid = scene
    gt = np.where(valid, scan.gt_depth, np.nan).astype(np.float32)
    out, info = repair_by_search(gt, _inputs(scan, patterns, valid), min_confidence=0.6)
    assert info["filled"] == 0
    assert info["switched"] <= 0.001 * valid.sum()
    kept = np.isfinite(out[valid])
    assert np.mean(out[valid][kept] != gt[valid][kept]) <= 0.001
    # the doubt rule drops a few right pixels that a confident wrong search contradicts (mostly at depth edges)
    assert (~kept).sum() == info["dropped"] <= 0.005 * valid.sum()


def test_doubt_drops_wrong_depths_and_keeps_right_ones(scene):
    scan, patterns, valid = scene
    gt = np.where(valid, scan.gt_depth, np.nan).astype(np.float32)
    depth = gt.copy()
    ys, xs = np.nonzero(valid)
    wrong = np.zeros_like(valid)
    # a 20 x 20 block of lit pixels given a surface 40 mm behind: another code (the field's kind of mistake)
    y, x = next((y, x) for y, x in zip(ys[::97], xs[::97]) if valid[y : y + 20, x : x + 20].all())
    wrong[y : y + 20, x : x + 20] = True
    depth[wrong] += 40.0
    out, info = doubt_by_search(depth, _inputs(scan, patterns, valid))
    # about half the block: the others' codes 40 mm off still fit with confidence >= 0.7 (6 patterns, no noise)
    assert np.isnan(out[wrong]).mean() > 0.4
    kept = wrong & np.isfinite(out)
    np.testing.assert_array_equal(out[kept], depth[kept])  # dropped or left, never replaced
    assert np.isfinite(out).sum() <= np.isfinite(depth).sum()  # nothing is filled
    rest = valid & ~wrong
    np.testing.assert_array_equal(out[rest][np.isfinite(out[rest])], depth[rest][np.isfinite(out[rest])])
    assert np.isnan(out[rest]).mean() <= 0.005  # few right pixels lost (a confident wrong search at depth edges)
    assert info["dropped"] == int(np.isnan(out[valid]).sum())


def test_neighbours_within_counts_the_agreeing_neighbours():
    d = np.full((4, 4), 100.0, np.float32)
    d[1, 1] = 150.0  # an isolated different depth: no neighbour agrees
    d[3, 3] = np.nan
    n = neighbours_within(d, 3.0)
    assert n[1, 1] == 0
    assert n[0, 0] == 2  # (0, 1), (1, 0) agree; (1, 1) does not
    assert n[2, 2] == 6  # 8 neighbours less (1, 1) and the NaN (3, 3)
    assert n[3, 3] == 0


def test_extract_depth_applies_the_doubt_rule_only_by_dropping(tiny_rods_field):
    """extract_depth with search_doubt: the same field's depth map, minus the pixels the rule drops (counted in
    timings["dropped"]["search_doubt"]), nothing added or moved (tiny has no refinement)."""
    from slwarp.neural.extraction import extract_depth

    _, cfg, trainer = tiny_rods_field
    trainer.cfg = cfg
    valid = trainer.renderer.valid_map.cpu().numpy()
    plain, _, _, t_plain, _ = extract_depth(trainer, valid)
    trainer.cfg = cfg.with_options(search_doubt=True)
    doubted, conf, _, t_doubt, _ = extract_depth(trainer, valid)
    assert "search_doubt" not in t_plain["dropped"]
    kept = np.isfinite(doubted)
    assert not (kept & ~np.isfinite(plain)).any()
    np.testing.assert_array_equal(doubted[kept], plain[kept])
    # a 60-iteration field leaves wrong depths on the rods for the rule to drop
    assert t_doubt["dropped"]["search_doubt"] == int((np.isfinite(plain) & ~kept).sum()) > 0
    assert np.isnan(conf[~kept]).all()
    # doubt_confidence is the rule's threshold: 0 drops nothing, 1 every contradicted depth (at least as many)
    dropped = {}
    for threshold in (0.0, 1.0):
        trainer.cfg = cfg.with_options(search_doubt=True, doubt_confidence=threshold)
        dropped[threshold] = extract_depth(trainer, valid)[3]["dropped"].get("search_doubt", 0)
    assert dropped[0.0] == 0 and dropped[1.0] >= t_doubt["dropped"]["search_doubt"]


def test_grow_repair_spreads_the_repaired_surface_to_its_wrong_neighbours(scene):
    """A patch that kept a surface 40 mm behind, in a block the repair fixed around it (the seeds): the growth gives
    the patch the seeds' surface pass by pass where the codes fit it better; a wrong block with no seed beside it,
    the right depths elsewhere and the holes stay as they were."""
    scan, patterns, valid = scene
    gt = np.where(valid, scan.gt_depth, np.nan).astype(np.float32)
    blocks = [(y, x) for y in range(10, 220, 15) for x in range(10, 270, 15)
              if valid[y : y + 30, x : x + 40].all() and np.ptp(scan.gt_depth[y : y + 30, x : x + 40]) < 15.0]
    y0, x0 = blocks[0]
    y1, x1 = next(b for b in blocks if abs(b[0] - y0) >= 40 or abs(b[1] - x0) >= 50)
    wrong = np.zeros_like(valid)
    wrong[y0 + 5 : y0 + 25, x0 + 30 : x0 + 38] = True  # 8 columns: within reach of the passes
    seeds = np.zeros_like(valid)
    seeds[y0 : y0 + 30, x0 : x0 + 40] = True  # around it on three sides, as a rod repaired on both sides of a gap
    seeds &= ~wrong
    lone = np.zeros_like(valid)
    lone[y1 : y1 + 10, x1 : x1 + 10] = True
    depth = gt.copy()
    depth[wrong | lone] += 40.0
    depth[5, :] = np.nan  # a hole stays a hole
    out, grown = grow_repair(depth, seeds, _inputs(scan, patterns, valid))
    assert grown[wrong].mean() > 0.9
    assert np.mean(np.abs(out[wrong] - gt[wrong]) < 2.0) > 0.9
    assert not grown[~wrong].any()  # the lone block, the seeds and the right depths elsewhere: untouched
    np.testing.assert_array_equal(out[~grown], depth[~grown])
    np.testing.assert_array_equal(np.isfinite(out), np.isfinite(depth))  # nothing dropped, nothing filled
    # without seeds nothing moves
    same, none = grow_repair(depth, np.zeros_like(valid), _inputs(scan, patterns, valid))
    assert not none.any()
    np.testing.assert_array_equal(same, depth)


def test_extract_depth_grows_the_repair_without_changing_completeness(tiny_rods_field):
    """extract_depth with repair_grow: the same map as without it except at the grown pixels (counted in
    timings["repair_grown"], fate "repaired"), no pixel gained or lost; the option needs search_repair."""
    from slwarp.neural.config import ConfigError
    from slwarp.neural.extraction import FATE, extract_depth

    _, cfg, trainer = tiny_rods_field
    with pytest.raises(ConfigError, match="repair_grow"):
        cfg.with_options(repair_grow=True)
    valid = trainer.renderer.valid_map.cpu().numpy()
    trainer.cfg = cfg.with_options(search_repair=True)
    plain = extract_depth(trainer, valid)
    trainer.cfg = cfg.with_options(search_repair=True, repair_grow=True)
    grown = extract_depth(trainer, valid)
    trainer.cfg = cfg
    assert "repair_grown" not in plain.timings
    np.testing.assert_array_equal(np.isfinite(grown.depth), np.isfinite(plain.depth))
    moved = np.isfinite(plain.depth) & (grown.depth != plain.depth)
    assert grown.timings["repair_grown"] == int(moved.sum())
    assert (grown.fate[moved] == FATE["repaired"]).all()
    np.testing.assert_array_equal(grown.fate[~moved], plain.fate[~moved])


def test_extract_depth_readmits_edge_pixels_and_only_them(tiny_rods_field):
    """extract_depth with edge_readmit: the pixels it gives back (timings["edge_readmitted"]) are ones the
    flying-pixel filter dropped without it, now with the field's depth and fate "measured"; every other pixel's
    depth is unchanged; the option needs the filter. The tiny field has few real depth edges, so a tight filter
    (half a footprint) and a readmission asking one neighbour and any confidence (the options
    edge_readmit_support and edge_readmit_confidence) exercise the plumbing (readmit_edge_pixels' own thresholds:
    tests/test_extract.py); the default bar gives back fewer."""
    from slwarp.neural.config import ConfigError
    from slwarp.neural.extraction import FATE, extract_depth

    _, cfg, trainer = tiny_rods_field
    with pytest.raises(ConfigError, match="edge_readmit"):
        cfg.with_options(edge_readmit=True, edge_filter=0.0)
    loose = dict(edge_readmit_support=1, edge_readmit_confidence=0.0)
    valid = trainer.renderer.valid_map.cpu().numpy()
    try:
        trainer.cfg = cfg.with_options(edge_filter=0.5)
        plain = extract_depth(trainer, valid)
        trainer.cfg = cfg.with_options(edge_filter=0.5, edge_readmit=True, **loose)
        back = extract_depth(trainer, valid)
        trainer.cfg = cfg.with_options(edge_filter=0.5, edge_readmit=True)
        strict = extract_depth(trainer, valid)
        trainer.cfg = cfg.with_options(edge_filter=0.0)
        unfiltered = extract_depth(trainer, valid)
    finally:
        trainer.cfg = cfg
    assert plain.timings["edge_readmitted"] == 0
    gained = np.isfinite(back.depth) & ~np.isfinite(plain.depth)
    assert back.timings["edge_readmitted"] >= int(gained.sum()) > 0
    assert (plain.fate[gained] == FATE["flying_pixel"]).all()
    assert (back.fate[gained] == FATE["measured"]).all()
    np.testing.assert_array_equal(back.depth[gained], unfiltered.depth[gained])
    kept = np.isfinite(plain.depth)
    np.testing.assert_array_equal(back.depth[kept], plain.depth[kept])
    assert back.timings["dropped"]["flying_pixel"] == plain.timings["dropped"]["flying_pixel"] - back.timings["edge_readmitted"]
    assert strict.timings["edge_readmitted"] < back.timings["edge_readmitted"]


def _brute_force_search(scan, patterns, valid, centres, radius, step_mm, exclude_mm=6.0, window_step=1):
    """(depth [P], best [P], second [P]) at centres [P, 2] (row, col): each window projects and samples its own
    pixels at every hypothesis (the torch twin's projection and bilinear taps), hypotheses in order, the rival
    the best cost more than `exclude` cells from the best (the search kernel's rule, written out in float64)."""
    from slwarp.scans.scanner import camera_rays
    from slwarp.neural import ops
    from slwarp.neural.ops import twin

    images = np.asarray(scan.images, np.float64)
    a, b = offset_and_modulation(images)
    near, far = scan.depth_range
    n_hyp = int(min(1024, max(16, np.ceil((far - near) / step_mm))))
    exclude = int(np.ceil(exclude_mm / ((far - near) / n_hyp)))
    rays = torch.tensor(camera_rays(scan.camera), dtype=torch.float64)
    prj = ops.pack_projector(scan.projector)
    pats = torch.as_tensor(patterns, dtype=torch.float64)
    H, W = valid.shape
    out = []
    for v, u in centres:
        taps = range(-radius * window_step, radius * window_step + 1, window_step)
        pix = [(v + dy, u + dx) for dy in taps for dx in taps if 0 <= v + dy < H and 0 <= u + dx < W and valid[v + dy, u + dx]]
        ys, xs = np.array(pix).T
        d = rays[ys, xs]  # [Q, 3]
        z = near + (far - near) * (np.arange(n_hyp) + 0.5) / n_hyp
        pts = d[None] * (torch.as_tensor(z)[:, None, None] / d[None, :, 2:])  # [n_hyp, Q, 3]
        uv, ok = twin.project_to_projector(pts.reshape(-1, 3), prj)
        p = twin.bilinear_patterns(pats, uv) * ok[:, None]  # [n_hyp * Q, N]
        pred = a[ys, xs][None, :, None] + b[ys, xs][None, :, None] * p.reshape(n_hyp, len(ys), -1).numpy()
        cost = np.abs(pred - images[:, ys, xs].T[None]).sum((1, 2)) / (len(ys) * len(images))
        best, best_h, rival = np.inf, -1, np.inf
        for h, c in enumerate(cost):
            if c < best:
                if best_h >= 0 and abs(h - best_h) > exclude:
                    rival = min(rival, best)
                best, best_h = c, h
            elif abs(h - best_h) > exclude:
                rival = min(rival, c)
        out.append((z[best_h], best, rival))
    return np.array(out).T


@pytest.mark.parametrize("radius,stride,window_step", [(1, 1, 1), (2, 2, 1), (1, 2, 3)])
def test_search_is_the_brute_force_window_search(scene, radius, stride, window_step):
    """search_depth's two passes (each pixel's cost once per hypothesis, then the windows' sums across blocks of
    hypotheses) give the brute-force search's answer: the best hypothesis of 40 centres, and where the ratio
    test is clear of rounding, the same confident ones; also with the window's pixels window_step px apart."""
    from slwarp.neural.start import search

    scan, patterns, valid = scene
    rng = np.random.default_rng(1)
    on_grid = np.argwhere(valid[::stride, ::stride]) * stride
    centres = on_grid[rng.choice(len(on_grid), 40, replace=False)]
    depth, best, rival = _brute_force_search(scan, patterns, valid, centres, radius, step_mm=2.0, window_step=window_step)
    old = search.SEARCH_BLOCK_VALUES
    try:
        search.SEARCH_BLOCK_VALUES = 37 * valid.size  # several blocks, the last one partly beyond the hypotheses
        kw = dict(radius=radius, window_step=window_step, stride=stride, step_mm=2.0, median=False)
        every = _search(scan, patterns, valid, ratio=1e9, **kw)
        confident = _search(scan, patterns, valid, ratio=0.8, **kw)
    finally:
        search.SEARCH_BLOCK_VALUES = old
    got = every[centres[:, 0], centres[:, 1]]
    np.testing.assert_allclose(got, depth, atol=1e-3)
    clear = np.abs(best - 0.8 * rival) > 1e-4
    assert clear.sum() > 30
    np.testing.assert_array_equal(np.isfinite(confident[centres[:, 0], centres[:, 1]])[clear], (best < 0.8 * rival)[clear])
