"""The extraction runner: a config's stages built in order (`build_stages`), run on one state (`run_stages`: each
timed, its pixels' fates recorded and the confidence of the depths it changed scored the same way for every stage),
and `extract_depth`, a trained field's depth map as its config's extraction section says.

Because every stage's new depths are scored, the confidence map is that of the final depth map: the refined and
the denoised depths are scored at their own depth (before stages, the map kept the confidence of the depth before
the refinement and the denoising). Only a stage that scores its depths itself (`Stage.scores`: the confidence
stage, the uniform-code fill with its neighbours' fit) is not scored again."""
from __future__ import annotations

import functools
import time

import numpy as np

from ..config import ConfigError, StageList
from .confidence import depth_confidence
from .stages import STAGES, Stage
from .state import Extraction, ModelInputs, State, TrainedField, register_fate

# every extraction ends with a depth map and its confidence map
REQUIRED_STAGES = ("depth", "confidence")


def build_stages(extraction) -> list[Stage]:
    """The stages an ExtractionConfig's `stages` names, in order, each with its settings. ConfigError naming the
    option when a name is no stage (STAGES), a required stage is missing or a stage comes before one it needs."""
    names = list(extraction.stages)
    unknown = [n for n in names if n not in STAGES]
    if unknown:
        raise ConfigError(f"option stages: no extraction stage {', '.join(map(repr, unknown))}; the stages are "
                          f"{', '.join(STAGES)}")
    missing = [n for n in REQUIRED_STAGES if n not in names]
    if missing:
        raise ConfigError(f"option stages: {StageList(names)} lacks {', '.join(missing)} (every extraction gives a "
                          "depth map and its confidence map; min_confidence 0 keeps every pixel)")
    stages = [STAGES[n].from_config(extraction) for n in names]
    for k, stage in enumerate(stages):
        before = [a for a in stage.after if a not in names[:k]]
        if before:
            raise ConfigError(f"option stages: {stage.name} needs {', '.join(before)} before it ({StageList(names)})")
    return stages


def run_stages(stages, state: State, score, on_stage=None) -> State:
    """The state after each stage in turn, each timed (timings[name + "_s"]) and settled (`_settle`). score(depth
    [H, W] mm, NaN elsewhere) -> confidence [H, W]: how the confidence of a changed depth is scored. on_stage(name,
    state), when given, sees the state after each stage (studies of what each stage did: bench.gross_errors)."""
    for stage in stages:
        t0 = time.perf_counter()
        after = stage(state)
        if after is not state:  # a stage with nothing to do returns its input
            after = _settle(stage, state, after, score)
        after.timings[f"{stage.name}_s"] = time.perf_counter() - t0
        state = after
        if on_stage is not None:
            on_stage(stage.name, state)
    return state


def _settle(stage: Stage, before: State, after: State, score) -> State:
    """After a stage: its info moved into timings, and where it changed the depth, the fate of the pixels it left
    without depth (stage.drops, else its name; counted in timings["dropped"]) and of those it gave a depth of its
    own (stage.marks: every new depth; else its name, the pixels that had none), the changed mask, and the
    confidence of the new depths scored (unless the stage scores them itself), NaN where no depth."""
    after.timings.update(after.info)
    if after.depth is None:
        return after.replace(info={})
    has = np.isfinite(after.depth)
    if before.depth is None:  # the first depth: every pixel inside inputs.valid had one to lose
        valid = before.inputs.valid
        had, new = (np.ones_like(has) if valid is None else np.asarray(valid, bool)), has
    else:
        had, new = np.isfinite(before.depth), has & ~(after.depth == before.depth)
    lost, gained = had & ~has, new & ~had
    fate = after.fate
    if stage.drops is not None or lost.any():
        fate[lost] = register_fate(stage.drops or stage.name)
        after.timings["dropped"][stage.drops or stage.name] = int(lost.sum())
    if stage.marks is not None or gained.any():
        fate[new if stage.marks is not None else gained] = register_fate(stage.marks or stage.name)
    confidence = after.confidence
    if confidence is not None:
        if not stage.scores and new.any():
            fresh = score(np.where(new, after.depth, np.nan).astype(np.float32))
            confidence = np.where(new, fresh, confidence).astype(np.float32)
        confidence = np.where(has, confidence, np.nan).astype(np.float32)
    return after.replace(confidence=confidence, changed=lost | new, info={})


def extract_depth(trainer, valid: np.ndarray | None = None, progress: bool = False, region: np.ndarray | None = None,
                  stages: list[Stage] | None = None, on_stage=None) -> Extraction:
    """An Extraction (depth [H, W], confidence [H, W], mesh, timings, fate [H, W]) of a trained field: the stages its
    config's `extraction.stages` names (or `stages`, built already: `build_stages`), run in order. valid [H, W]: the
    pixels the depth map may cover (default: every pixel); region [H, W]: where the uniform-code fill may add pixels
    (default: anywhere); progress: a bar for the marching cubes. The confidence is the term `extraction.confidence`.
    timings: seconds per stage (name + "_s"), "dropped" (the pixels each stage left without depth, by fate) and the
    counts the stages report (edge_readmitted, repair, refine_misfit, refined, refine_check, filled_uniform,
    repair_grown); fate: state.pixel_fates()'s index per pixel. on_stage: as run_stages'."""
    ex = trainer.cfg.extraction
    stages = build_stages(ex) if stages is None else stages
    # the pattern model's inputs, once (on a GPU its own tensors), and the trained field
    inputs = ModelInputs.from_trainer(trainer, valid, region)
    field = TrainedField.from_trainer(trainer)
    score = functools.partial(depth_confidence, inputs, kind=ex.confidence, field=field)
    state = run_stages(stages, State.start(inputs, field, progress), score, on_stage)
    return Extraction(state.depth, state.confidence, state.mesh, state.timings, state.fate)
