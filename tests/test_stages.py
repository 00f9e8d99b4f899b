"""The extraction as stages (slwarp.neural.extraction): the runner's bookkeeping (times, fates, drops, the changed
mask, the confidence scored after a stage), the checks of a stage list, a new stage named in a preset's list, and
the config's `stages` option with the stage switches of old (flat options that add or remove their stage)."""
from __future__ import annotations

import dataclasses
import types
from dataclasses import dataclass

import numpy as np
import pytest

from slwarp.neural.config import (DEFAULT_STAGES, OPTIONS, PRESETS, STAGE_ORDER, STAGE_SWITCHES, ConfigError,
                                  TrainConfig, load_config, parse_assignments, preset, save_config)
from slwarp.neural.extraction import (FATE, PIXEL_FATES, STAGES, ModelInputs, Stage, State, TrainedField,
                                      build_stages, pixel_fates, run_stages)
from slwarp.neural.extraction.stages import unregister_stage
from slwarp.neural.extraction.state import forget_fate

H, W = 4, 6


@pytest.fixture
def toy_stages():
    """Stages defined for a test (names starting with "toy_"), removed from STAGES and their fates forgotten after."""
    before = set(STAGES)
    fates = set(pixel_fates())
    yield
    for name in set(STAGES) - before:
        unregister_stage(name)
    for fate in reversed(pixel_fates()):
        if fate not in fates:
            forget_fate(fate)


def _state(valid=None) -> State:
    """A state over a 4 x 6 camera with no trained field (the runner's bookkeeping needs none)."""
    camera = types.SimpleNamespace(height=H, width=W)
    inputs = ModelInputs(camera, None, np.zeros((2, H, W), np.float32), np.zeros((2, 3, 3), np.float32),
                         (100.0, 200.0), valid=valid)
    return State.start(inputs, TrainedField(None, None, None, 0))


def _toy_classes():
    """Toy stages: a depth map, a filter that drops the first row (its fate declared), one that drops the last
    column (undeclared: its own name), one that gives the pixels without depth 150 mm marked as "repaired", one that
    moves every depth by 1 mm, and a confidence of 0.5 everywhere with depth."""

    @dataclass(frozen=True)
    class ToyDepth(Stage):
        name = "toy_depth"
        drops = "no_surface"
        after = ()

        def __call__(self, state):
            depth = np.full((H, W), 120.0, np.float32)
            depth[1, 1] = np.nan
            if state.inputs.valid is not None:
                depth = np.where(state.inputs.valid, depth, np.nan).astype(np.float32)
            return state.replace(depth=depth)

    @dataclass(frozen=True)
    class ToyRow(Stage):
        name = "toy_row"
        drops = "toy_row_fate"
        after = ("toy_depth",)

        def __call__(self, state):
            depth = state.depth.copy()
            depth[0] = np.nan
            return state.replace(depth=depth, info={"toy_rows": 1})

    @dataclass(frozen=True)
    class ToyColumn(Stage):
        name = "toy_column"
        after = ("toy_depth",)

        def __call__(self, state):
            depth = state.depth.copy()
            depth[:, -1] = np.nan
            return state.replace(depth=depth)

    @dataclass(frozen=True)
    class ToyFill(Stage):
        name = "toy_fill"
        marks = "repaired"
        after = ("toy_depth",)

        def __call__(self, state):
            return state.replace(depth=np.where(np.isfinite(state.depth), state.depth, 150.0).astype(np.float32))

    @dataclass(frozen=True)
    class ToyMove(Stage):
        name = "toy_move"
        after = ("toy_depth",)

        def __call__(self, state):
            return state.replace(depth=state.depth + 1.0)

    @dataclass(frozen=True)
    class ToyScore(Stage):
        name = "toy_score"
        scores = True
        after = ("toy_depth",)

        def __call__(self, state):
            return state.replace(confidence=np.where(np.isfinite(state.depth), 0.5, np.nan).astype(np.float32))

    @dataclass(frozen=True)
    class ToyIdle(Stage):
        name = "toy_idle"
        drops = "toy_idle_fate"
        after = ()

        def __call__(self, state):
            return state

    return ToyDepth(), ToyRow(), ToyColumn(), ToyFill(), ToyMove(), ToyScore(), ToyIdle()


def _scorer(calls):
    """A confidence score of 0.9 that records the depth maps it was asked about."""

    def score(depth):
        calls.append(depth.copy())
        return np.where(np.isfinite(depth), 0.9, np.nan).astype(np.float32)

    return score


def test_the_runner_times_each_stage_and_records_fates_and_drops(toy_stages):
    depth_, row, column, fill, move, score_, idle = _toy_classes()
    valid = np.ones((H, W), bool)
    valid[3, 0] = False
    state = run_stages([idle, depth_, row, column], _state(valid), _scorer([]))
    for name in ("toy_idle", "toy_depth", "toy_row", "toy_column"):
        assert state.timings[name + "_s"] >= 0.0
    names = pixel_fates()
    assert names[: len(PIXEL_FATES)] == PIXEL_FATES and {"toy_row_fate", "toy_column"} <= set(names)
    fate = np.array(names)[state.fate]
    assert fate[3, 0] == "no_contrast" and fate[1, 1] == "no_surface"
    assert (fate[0] == "toy_row_fate").all()  # the first row's pixels all had depth before the row filter
    assert (fate[1:, -1] == "toy_column").all()  # an undeclared fate: the stage's name
    assert (fate[np.isfinite(state.depth)] == "measured").all()
    assert np.isfinite(state.depth).sum() == (fate == "measured").sum() == (H - 1) * (W - 1) - 2
    # drops counted per fate over the pixels that had depth; a stage that returns its input counts nothing
    assert state.timings["dropped"] == {"no_surface": 1, "toy_row_fate": W, "toy_column": H - 1}
    assert state.timings["toy_rows"] == 1 and "toy_idle_fate" not in state.timings["dropped"]
    expect = np.zeros((H, W), bool)
    expect[1:, -1] = True
    np.testing.assert_array_equal(state.changed, expect)  # the last stage's: the column
    assert state.confidence is None  # no stage scored


def test_the_runner_scores_the_confidence_of_changed_depths_only(toy_stages):
    depth_, row, column, fill, move, score_, idle = _toy_classes()
    calls = []
    state = run_stages([depth_, row, score_], _state(), _scorer(calls))
    assert not calls  # before the first map and by the stage that scores: no scoring
    np.testing.assert_array_equal(state.confidence, np.where(np.isfinite(state.depth), 0.5, np.nan))
    state = run_stages([fill], state, _scorer(calls))
    (asked,) = calls
    filled = np.zeros((H, W), bool)
    filled[0] = True
    filled[1, 1] = True
    np.testing.assert_array_equal(np.isfinite(asked), filled)  # only the pixels the stage gave a depth
    np.testing.assert_array_equal(state.confidence, np.where(filled, 0.9, 0.5).astype(np.float32))
    assert (state.fate[filled] == FATE["repaired"]).all()  # marks: every new depth
    state = run_stages([column], state, _scorer(calls))
    assert len(calls) == 1 and np.isnan(state.confidence[:, -1]).all()  # no depth, no confidence
    state = run_stages([move], state, _scorer(calls))
    assert np.isfinite(calls[-1]).sum() == np.isfinite(state.depth).sum()  # a moved depth is scored again
    assert (state.fate[filled & np.isfinite(state.depth)] == FATE["repaired"]).all()  # and keeps its fate


def test_stage_lists_are_checked_when_built(toy_stages):
    _toy_classes()
    ex = preset("tiny").extraction
    stages = build_stages(ex)
    assert [s.name for s in stages] == list(DEFAULT_STAGES)
    assert stages[3].edge_filter == ex.edge_filter and stages[4].min_confidence == ex.min_confidence
    for names, match in (((*DEFAULT_STAGES, "nope"), "no extraction stage 'nope'"),
                         (("marching_cubes", "depth", "flying_pixel"), "lacks confidence"),
                         (("depth", "confidence"), "depth needs marching_cubes before it"),
                         (("marching_cubes", "toy_row", "depth", "confidence"), "toy_row needs toy_depth")):
        with pytest.raises(ConfigError, match=match):
            build_stages(dataclasses.replace(ex, stages=names))
    # sphere tracing needs no mesh
    sphere = dataclasses.replace(ex, stages=("depth", "confidence"), depth_method="sphere")
    assert [s.name for s in build_stages(sphere)] == ["depth", "confidence"]


def test_every_setting_of_a_stage_is_an_extraction_option():
    """The built-in stages read extraction options by their flat names, and every extraction option is some stage's
    setting but the list itself and the switches that only say whether a stage runs."""
    settings = set()
    for name in STAGE_ORDER:
        for f in dataclasses.fields(STAGES[name]):
            assert OPTIONS[f.name].section == "extraction", (name, f.name)
            settings.add(f.name)
    extraction = {name for name, opt in OPTIONS.items() if opt.section == "extraction"}
    assert extraction - settings == {"stages"} | {o for o in STAGE_SWITCHES if OPTIONS[o].is_bool}
    assert {o for o in STAGE_SWITCHES if not OPTIONS[o].is_bool} <= settings  # a number that is 0 when off


def test_reconstruct_refuses_an_unknown_stage_before_training():
    from slwarp.neural.reconstruct import reconstruct

    cfg = preset("tiny", stages=(*DEFAULT_STAGES, "no_such_stage"))
    with pytest.raises(ConfigError, match="no_such_stage"):
        reconstruct(None, cfg, progress=False)  # no scan: the list is refused before the trainer reads one


def test_a_stage_inserted_into_a_presets_list_runs_timed_and_recorded_in_the_fate(tiny_rods_field, toy_stages):
    """A new stage is one class named in a list: here one that drops the upper half of the depth map, inserted
    before the confidence stage of `tiny`; it runs in its place (the confidence stage after it scores what it left),
    is timed, and its pixels' fate and count say so; every other pixel is as without it."""
    from slwarp.neural.extraction import extract_depth

    @dataclass(frozen=True)
    class UpperHalf(Stage):
        name = "toy_upper_half"
        drops = "toy_upper"

        def __call__(self, state):
            depth = state.depth.copy()
            depth[: depth.shape[0] // 2] = np.nan
            return state.replace(depth=depth)

    _, cfg, trainer = tiny_rods_field
    lit = trainer.renderer.valid_map.cpu().numpy()
    stages = list(cfg.extraction.stages)
    stages.insert(stages.index("confidence"), "toy_upper_half")
    try:
        trainer.cfg = cfg
        plain = extract_depth(trainer, lit)
        trainer.cfg = cfg.with_options(stages=tuple(stages))
        got = extract_depth(trainer, lit)
    finally:
        trainer.cfg = cfg
    half = np.zeros(lit.shape, bool)
    half[: lit.shape[0] // 2] = True
    upper = pixel_fates().index("toy_upper")
    assert got.timings["toy_upper_half_s"] >= 0.0
    assert list(got.timings).index("toy_upper_half_s") < list(got.timings).index("confidence_s")
    had = half & np.isfinite(plain.depth)
    # the pixels the new stage dropped: those with depth before the confidence filter, so at least the final ones
    assert had.sum() > 0 and (got.fate[had] == upper).all()
    assert got.timings["dropped"]["toy_upper"] == int((got.fate == upper).sum())
    assert np.isnan(got.depth[half]).all() and np.isnan(got.confidence[half]).all()
    np.testing.assert_array_equal(got.depth[~half], plain.depth[~half])
    np.testing.assert_array_equal(got.fate[~half], plain.fate[~half])
    assert got.timings["dropped"]["low_confidence"] == int((got.fate == FATE["low_confidence"]).sum())


def test_the_confidence_map_is_that_of_the_final_depth(tiny_rods_field):
    """The runner scores every depth a stage moves, the refined and the denoised ones too: the map written beside
    the depth is the photometric confidence of the final depth map at every pixel with depth."""
    from slwarp.neural.pattern_model import photometric_confidence
    from slwarp.neural.extraction import extract_depth

    _, cfg, trainer = tiny_rods_field
    lit = trainer.renderer.valid_map.cpu().numpy()
    try:
        trainer.cfg = cfg.with_options(refine_range=1.0, denoise_radius=2)
        got = extract_depth(trainer, lit)
    finally:
        trainer.cfg = cfg
    assert got.timings["refined"] and list(got.timings)[-1] == "denoise_s"
    want = photometric_confidence(got.depth, *ModelInputs.from_trainer(trainer, lit).model)
    np.testing.assert_array_equal(got.confidence, want)


# --- the config's list and the switches of old -----------------------------------------------------------------


def test_presets_name_their_stages_and_the_switches_read_from_the_list():
    tuned = PRESETS["tuned"].extraction
    assert tuned.stages == (*DEFAULT_STAGES, "search_repair", "refine", "uniform_fill", "repair_grow", "denoise")
    assert tuned.search_repair and tuned.search_doubt and tuned.uniform_fill and tuned.repair_grow
    assert tuned.refine_range == 3.0 and tuned.denoise_radius == 4 and tuned.edge_filter == 10.0
    for name in ("paper", "cpu", "tiny"):
        ex = PRESETS[name].extraction
        assert ex.stages == DEFAULT_STAGES and not (ex.search_repair or ex.search_doubt or ex.uniform_fill)
        assert ex.refine_range == 0.0 and ex.denoise_radius == 0
    assert str(tuned.stages).startswith("marching_cubes,depth,depth_range,")  # as --help and --stages write it


def test_switches_add_and_remove_their_stage_in_its_place():
    cpu = preset("cpu", refine_range=2.0, denoise_radius=1)
    assert cpu.extraction.stages == (*DEFAULT_STAGES, "refine", "denoise")
    off = cpu.with_options(edge_filter=0.0, refine_range=0.0)
    assert off.extraction.stages == ("marching_cubes", "depth", "depth_range", "confidence", "denoise")
    assert off.extraction.edge_filter == 0.0 and off.extraction.refine_range == 0.0
    back = off.with_options(edge_filter=5.0, uniform_fill=True)
    assert back.extraction.stages == (*DEFAULT_STAGES, "uniform_fill", "denoise")
    # a stage the order does not know keeps its place; a switched stage goes right after the last known one before it
    custom = preset("tiny", stages=("marching_cubes", "depth", "toy_x", "confidence"))
    assert custom.with_options(edge_filter=3.0).extraction.stages == (
        "marching_cubes", "depth", "flying_pixel", "toy_x", "confidence")
    with pytest.raises(ConfigError, match="refine runs with refine_range above 0"):
        preset("tiny", stages=(*DEFAULT_STAGES, "refine"))
    with pytest.raises(ConfigError, match="edge_readmit"):
        preset("tiny", edge_filter=0.0, edge_readmit=True)
    with pytest.raises(ConfigError, match="repair_grow"):
        preset("tiny", repair_grow=True)


def test_search_repair_and_its_doubt_rule_share_one_place():
    """search_doubt is the repair's "else": turning the repair off leaves the doubt rule where a run asked for it
    (tuned does), and nothing where it did not; naming both in the list is refused."""
    tuned = PRESETS["tuned"]
    doubt = tuned.with_options(search_repair=False, repair_grow=False).extraction
    assert "search_doubt" in doubt.stages and "search_repair" not in doubt.stages and doubt.search_doubt
    assert doubt.stages.index("search_doubt") == tuned.extraction.stages.index("search_repair")
    none = tuned.with_options(search_doubt=False).with_options(search_repair=False, repair_grow=False).extraction
    assert not set(none.stages) & {"search_repair", "search_doubt"} and not none.search_doubt
    assert preset("cpu", search_repair=True).with_options(search_repair=False).extraction.stages == DEFAULT_STAGES
    assert preset("cpu", search_doubt=True).extraction.stages == (*DEFAULT_STAGES, "search_doubt")
    with pytest.raises(ConfigError, match="name one"):
        preset("tiny", stages=(*DEFAULT_STAGES, "search_repair", "search_doubt"))


def test_stage_lists_in_files_and_on_the_command_line(tmp_path):
    """A config file keeps the list (and reads back equal); a file of before lists (flat switches only) sets the
    list through its switches; the command line's list is comma-separated."""
    save_config(tmp_path / "tuned.yaml", PRESETS["tuned"])
    assert load_config(tmp_path / "tuned.yaml", base=PRESETS["cpu"]) == PRESETS["tuned"]
    old = tmp_path / "old.yaml"
    old.write_text("extraction:\n  edge_filter: 0.0\n  edge_readmit: false\n  search_repair: false\n"
                   "  repair_grow: false\n  uniform_fill: false\n")
    ex = load_config(old, base=PRESETS["tuned"]).extraction
    assert ex.stages == ("marching_cubes", "depth", "depth_range", "confidence", "search_doubt", "refine", "denoise")
    assert parse_assignments(["stages=marching_cubes, depth,confidence"]) == {
        "stages": ("marching_cubes", "depth", "confidence")}
    for bad in ("stages=depth,,confidence", "stages=depth,2d"):
        with pytest.raises(ConfigError, match="comma-separated list of names"):
            parse_assignments([bad])
    with pytest.raises(ConfigError, match="named more than once"):
        TrainConfig().with_options(stages=("marching_cubes", "depth", "depth", "confidence"))
