"""The search repair at extraction: a per-pixel depth search (`start.search.search_depth`) against the field's depth map.

- `repair_by_search`: holes filled and contradicted depths replaced where the searches agree and the codes fit
  clearly better, kept only where neighbours (and, as asked, a large connected group) confirm them; contradicted
  depths the codes do not support dropped.
- `doubt_by_search`: that doubt rule alone (drops, never fills or replaces).
- `grow_repair`: the repair's changes spread to neighbours that kept another surface's depth.

All take the pattern model's inputs as one bundle (`state.ModelInputs`); patterns as rendered (blurred).
"""
from __future__ import annotations

import cv2
import numpy as np

from ...devices import torch_device
from ..depth_maps import AGREE_MM, component_sizes, neighbours_within
from ..config.sections import DOUBT_CONFIDENCE
from ..pattern_model import photometric_confidence
from ..start.search import search_depth
from .state import ModelInputs


# a pixel's depth and a confident search's answer "disagree" beyond this (mm): the search's own exclusion zone
DISAGREE_MM = 6.0
# a hole takes a search depth whose photometric confidence is at least this (small-rig bunny and rods: 0.8 halves
# the wrong fills of 0.6 and keeps 95% of the right ones)
FILL_CONFIDENCE = 0.8
# a change is kept where at least this many of the pixel's 8 neighbours end within AGREE_MM of it
SUPPORT = 2
# a depth is replaced by a search's whose photometric confidence is higher by this (rods: 0.1 fixes 109 pixels
# and breaks 11, 0.0 fixes 128 and breaks 61)
SWITCH_MARGIN = 0.1

# the camera a repair_min_component counts its pixels on: the full-resolution rigs' and the real captures' (1280 x 1024)
COMPONENT_REFERENCE_PIXELS = 1280 * 1024
# the smallest group a scaled size asks for: on the small rigs (1/16 of the pixels) 6 let a few groups of wrong fills
# in (bunny RMSE 1.43 -> 2.06 mm, vertical-rig vase 0.43 -> 0.89), 8 and 10 did not
# (bench/results/accuracy-cpu-repair-footprint-8-10.md)
MIN_SCALED_COMPONENT = 10


def scaled_min_component(min_component: int, shape) -> int:
    """The repair's group size for an image of `shape` (H, W, ...): `min_component` as given for a 1280 x 1024 camera,
    scaled by the pixel count where the image has fewer (the same view in fewer, larger pixels: a group covering the
    same surface holds fewer of them), but not below MIN_SCALED_COMPONENT (nor above what was given); unchanged for
    larger images; 0 stays 0 (off). Why: 100 pixels, right at full resolution, cover 16x the surface on a quarter-size
    camera; there 10 took the small rigs' steps from 0.83x to 0.73x GC(7)'s MAE and rods from 0.76x / 0.75x to
    0.72x / 0.71x (bench/results/accuracy-cpu-repair-footprint*.md)."""
    if min_component <= 0:
        return 0
    ratio = min(1.0, int(shape[0]) * int(shape[1]) / COMPONENT_REFERENCE_PIXELS)
    return max(min(min_component, MIN_SCALED_COMPONENT), round(min_component * ratio))


def repair_by_search(depth: np.ndarray, inputs: ModelInputs, min_confidence: float, *, margin: float = SWITCH_MARGIN,
                     fill_confidence: float = FILL_CONFIDENCE, support: int = SUPPORT,
                     doubt_confidence: float = DOUBT_CONFIDENCE, min_component: int = 0) -> tuple[np.ndarray, dict]:
    """(depth [H, W] repaired, info) where a per-pixel depth search contradicts the field.

    Why: a field can miss what few rays saw (rods a few pixels wide, small parts behind a depth edge). Its
    depth there is the background's, or none once the filters drop it, while a search along each ray still
    finds the thin surface (small-rig rods: 2411 of 3472 rod pixels within 5 mm, against none from the field).
    A search answer counts where it is confident with a 3x3 window and a 5x5 window agrees (within AGREE_MM):
    single answers of either put wrong depths into 20-30% of the holes they fill (bench/repair_study.py).
    Judged by the photometric confidence (1 - relative RMS residual, `pattern_model.photometric_confidence`;
    patterns as rendered, blurred):
    - holes: a lit pixel in `valid` without depth takes the search's depth when its confidence there is
      >= max(min_confidence, fill_confidence);
    - contradictions: a pixel whose depth is more than DISAGREE_MM from the search's takes the search's depth when
      the search's confidence beats the pixel's by `margin`;
    - either change stays only where `support` of the pixel's 8 neighbours end within AGREE_MM of it (an isolated
      change is a chance match of the codes);
    - with min_component > 0, a change also stays only inside a connected group (8 neighbours, each within
      AGREE_MM of the next) of at least min_component changed pixels: a thin part the field missed is a long
      run of pixels, while the search's chance matches come in small clusters that overlapping windows share;
    - doubts: a contradicted depth that is not replaced is dropped when its confidence is below `doubt_confidence`
      (on rods, the background's depth on a rod pixel the 5x5 search cannot confirm) or when the switch's
      confidence test passed but the neighbour or group rule refused it.
    The searches run over `inputs.valid` (default: the lit pixels) with inputs.step_mm on inputs.device, their windows'
    pixels inputs.window_step px apart (a set designed for spaced windows tells chance matches apart only so). The caller
    refines the result (`pattern_model.refine_depth`). info: counts of holes, filled, contested, switched and
    dropped pixels."""
    depth = np.asarray(depth, np.float32)
    valid = _searched(inputs)
    out = depth.copy()
    common = dict(step_mm=inputs.step_mm, stride=1, window_step=inputs.window_step, device=inputs.device)
    s1, contested = _contested(depth, inputs, valid, **common)
    has = np.isfinite(depth)
    holes = valid & ~has & np.isfinite(s1)
    info = {"holes": int((valid & ~has).sum()), "filled": 0, "contested": int(contested.sum()), "switched": 0}
    if not (holes.any() or contested.any()):
        return out, info
    s2, _ = search_depth(*inputs.model, inputs.depth_range, valid=valid, radius=2, centres=holes | contested, **common)
    agree = np.isfinite(s2) & (np.abs(s2 - s1) < AGREE_MM)
    conf_s = photometric_confidence(np.where(agree, s1, np.nan), *inputs.model)
    fill = holes & agree & (conf_s >= max(min_confidence, fill_confidence))
    conf_d = photometric_confidence(np.where(contested, depth, np.nan), *inputs.model)
    better = contested & agree & (conf_s > conf_d + margin)  # the codes fit the search's depth clearly better
    switch = better.copy()
    out[fill | switch] = s1[fill | switch]
    change = fill | switch
    if support > 0 and change.any():
        # an isolated change is a search's chance match: keep those that `support` of their 8 neighbours agree with
        agreeing = neighbours_within(out, AGREE_MM, device=torch_device(inputs.device))
        drop = change & (agreeing < support)
        out[drop] = depth[drop]
        fill &= ~drop
        switch &= ~drop
    if min_component > 0 and (fill | switch).any():
        small = (fill | switch) & (component_sizes(np.where(fill | switch, out, np.nan), AGREE_MM) < min_component)
        out[small] = depth[small]
        fill &= ~small
        switch &= ~small
    # a contradicted depth that stays is dropped when the codes do not support it, or when they fit the search's
    # depth clearly better but its neighbours did not confirm the switch (rods: the background's depth on a rod
    # pixel is otherwise left in place)
    doubt = contested & ~switch & ((conf_d < doubt_confidence) | better)
    out[doubt] = np.nan
    info.update(filled=int(fill.sum()), switched=int(switch.sum()), dropped=int(doubt.sum()))
    return out, info


def _searched(inputs: ModelInputs) -> np.ndarray:
    """[H, W] bool: the pixels the repair's searches cover: inputs.valid, or the lit ones when it names none."""
    return np.asarray(inputs.lit if inputs.valid is None else inputs.valid, bool)


def _contested(depth, inputs: ModelInputs, valid, **common):
    """(s1 [H, W], contested [H, W] bool): the 3x3-window search's depth and the pixels in `valid` whose depth
    it contradicts by more than DISAGREE_MM."""
    s1, _ = search_depth(*inputs.model, inputs.depth_range, valid=valid, radius=1, **common)
    with np.errstate(invalid="ignore"):
        contested = valid & np.isfinite(depth) & np.isfinite(s1) & (np.abs(s1 - depth) > DISAGREE_MM)
    return s1, contested


def doubt_by_search(depth: np.ndarray, inputs: ModelInputs, *,
                    doubt_confidence: float = DOUBT_CONFIDENCE) -> tuple[np.ndarray, dict]:
    """(depth [H, W] with its doubtful pixels NaN, info): the search repair's doubt rule alone.

    A pixel whose depth a 3x3-window depth search contradicts by more than DISAGREE_MM and whose photometric
    confidence is below `doubt_confidence` is dropped; nothing is filled or replaced. Why without the rest: a
    search's fills and switches are single-pixel chance matches of 6 codes that neighbouring windows repeat
    (on the full-resolution GPU sweep they put 0.2-0.5% of the pixels of every smooth scene off by > 5 mm),
    while the doubt rule only removes depth: on thin parts, the background's depth the field left there.
    The search as the repair's (`inputs.valid`, step and device). info: counts of contested and dropped pixels."""
    depth = np.asarray(depth, np.float32)
    _, contested = _contested(depth, inputs, _searched(inputs), step_mm=inputs.step_mm, stride=1,
                              window_step=inputs.window_step, device=inputs.device)
    conf_d = photometric_confidence(np.where(contested, depth, np.nan), *inputs.model)
    doubt = contested & (conf_d < doubt_confidence)
    out = depth.copy()
    out[doubt] = np.nan
    return out, {"contested": int(contested.sum()), "dropped": int(doubt.sum())}


# a neighbour's depth "differs" from a pixel's beyond this (mm) in the repair's growth: another surface, not the
# same one bent (thin rods stand tens to hundreds of mm before their background)
GROW_DIFFER_MM = 20.0
# passes of the repair's growth at most (each moves its front by one pixel)
GROW_PASSES = 10
# a pixel takes the repaired surface only with at least this many repaired (or grown) pixels among its 8 neighbours.
# Full-resolution rods, tuned's maps (H100; offline, after the extraction): with 1 / 2 / 3 the growth set 30 / 25 / 20
# pixels right (within 3 mm) and 33 / 21 / 5 wrong (over 20 mm) on the default rig, 127 / 122 / 104 right and
# 105 / 29 / 9 wrong on the rolled one; 3 has the fewest wrong switches on all four rigs
GROW_SUPPORT = 3


def grow_repair(depth: np.ndarray, seeds: np.ndarray, inputs: ModelInputs, *, margin: float = 0.0,
                support: int = GROW_SUPPORT, differ_mm: float = GROW_DIFFER_MM,
                passes: int = GROW_PASSES) -> tuple[np.ndarray, np.ndarray]:
    """(depth [H, W], grown [H, W] bool): the search repair's changes spread to the neighbouring pixels that
    kept the other surface's depth, where the codes fit the repaired surface better.

    Why: where the field loses a stretch of a thin part (a rod a few pixels wide), its pixels carry the
    background's depth. The filters drop most of them, but with 6 binary codes about one in ten fits the wrong
    depth by chance and stays; the repair switches a pixel only in a large confirmed group, so those scattered
    survivors beside the repaired rod stay 100-300 mm off. Full-resolution vertical-rig rods (tuned, H100): 495
    pixels off by > 20 mm, 0.05% of the map, carry 0.149 of its 0.285 mm MAE; 13% of their 5x5 neighbourhood
    is repaired, against 0.4% for the map as a whole.
    Each pass takes the pixels with depth that have at least `support` grown or seed pixels among their 8
    neighbours, whose mean depth differs from theirs by more than `differ_mm`, and gives them that mean where its
    photometric confidence (`pattern_model.photometric_confidence`; patterns as rendered) beats theirs by more than
    `margin`. Nothing is dropped and no hole is filled: the map keeps its completeness. seeds [H, W] bool: the
    repair's changes. Cost: two confidences at the candidate pixels per pass."""
    out = np.asarray(depth, np.float32).copy()
    has = np.isfinite(out)
    grown_or_seed = np.asarray(seeds, bool) & has
    grown = np.zeros_like(has)
    for _ in range(passes):
        w = grown_or_seed.astype(np.float32)
        total = cv2.boxFilter(np.where(grown_or_seed, out, 0.0).astype(np.float32), -1, (3, 3), normalize=False,
                              borderType=cv2.BORDER_CONSTANT)
        count = cv2.boxFilter(w, -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
        mean = total / np.maximum(count, 1.0)
        with np.errstate(invalid="ignore"):
            candidate = has & ~grown_or_seed & (count >= support) & (np.abs(out - mean) > differ_mm)
        if not candidate.any():
            break
        # both confidences at the candidates only (photometric_residual's sparse path)
        conf = photometric_confidence(np.where(candidate, out, np.nan).astype(np.float32), *inputs.model)
        conf_new = photometric_confidence(np.where(candidate, mean, np.nan).astype(np.float32), *inputs.model)
        switch = candidate & (conf_new > conf + margin)
        if not switch.any():
            break
        out[switch] = mean[switch]
        grown |= switch
        grown_or_seed |= switch
    return out, grown
