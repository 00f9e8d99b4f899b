"""The uniform-code fill at extraction: lit pixels without contrast (a projector square black or white in every
pattern) given the field's depth where the codes it predicts there explain the images (`fill_uniform_codes`)."""
from __future__ import annotations

import numpy as np

from ..pattern_model import MIN_MODULATION, offset_and_modulation, projector_coords_at, sample_patterns_at
from ..depth_maps import AGREE_MM, neighbours_within
from .state import ModelInputs

# uniform-code fill (`fill_uniform_codes`): how far each predicted code may lie from all-black (0) or all-white
# (1), the window (radius px) whose lit pixels lend their offset and modulation and their depth correction, and
# the share of that window that must be lit with contrast
UNIFORM_TOLERANCE = 0.25
UNIFORM_RADIUS = 7
UNIFORM_MIN_SHARE = 0.25
UNIFORM_CORRECTION_RADIUS = 3
# the refinement moves a depth by at most refine_range (3 mm in the presets); a larger depth - field_depth is a
# search repair (a rod the field missed: about 100 mm) and says nothing about the field's local error
UNIFORM_CORRECTION_MAX_MM = 3.0


def _box_mean(values: np.ndarray, weight: np.ndarray, radius: int) -> tuple[np.ndarray, np.ndarray]:
    """(mean of values over the weighted pixels of each (2 radius + 1)^2 window, that window's weight sum)."""
    import cv2

    k = (2 * radius + 1, 2 * radius + 1)
    w = weight.astype(np.float32)
    total = cv2.boxFilter(np.where(w > 0, values, 0.0).astype(np.float32), -1, k, normalize=False,
                          borderType=cv2.BORDER_CONSTANT)
    count = cv2.boxFilter(w, -1, k, normalize=False, borderType=cv2.BORDER_CONSTANT)
    return total / np.maximum(count, 1e-6), count


def fill_uniform_codes(depth: np.ndarray, field_depth: np.ndarray, inputs: ModelInputs,
                       min_confidence: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(depth [H, W], confidence [H, W] of the filled pixels (NaN elsewhere), filled [H, W] bool): the field's
    depth given to lit pixels that have too little contrast to take part, where the codes it predicts explain them.

    Why: with 6 random binary patterns some projector squares are black (or white) in every pattern, so the
    camera pixels they light have no modulation b; they leave the training and the depth map (1.2 to 2.8% of the
    lit pixels of most virtual-scanner scans, GPU default rig and others) although the field has a surface there,
    held by its neighbours.
    A pixel without contrast (not `inputs.lit`, inside `inputs.region`) and without depth takes the field's depth
    field_depth [H, W] (mm, within inputs.depth_range) when:
    - the patterns (as rendered, blurred) predict codes there within UNIFORM_TOLERANCE of all 0 or all 1, and the
      point projects inside the projector image (a point off it, or in its shadow, also reads dark; a shadow
      mostly predicts mixed codes, but now and then all black: 17 of 559 fills on the small-rig steps, at the
      surface's depth);
    - UNIFORM_MIN_SHARE of its (2 UNIFORM_RADIUS + 1)^2 window is lit with contrast, and the images fit a + b Q
      with that window's mean offset a and modulation b: 1 - relative RMS residual >= min_confidence;
    - two of its 8 neighbours end within depth_maps.AGREE_MM of its depth.
    Its depth is then corrected by the mean of depth - field_depth over the pixels in its
    (2 UNIFORM_CORRECTION_RADIUS + 1)^2 window where that difference is within UNIFORM_CORRECTION_MAX_MM (the
    refinement's local correction of the field, which a pixel without contrast cannot measure itself; small-rig
    spheres: filled pixels 0.92 -> 0.60 mm MAE).
    depth: the map so far (mm, NaN: none); the images and the patterns as rendered, on the host (inputs.host_images
    [N, H, W], inputs.host_patterns [N, Hp, Wp], in [0, 1])."""
    depth = np.asarray(depth, np.float32)
    field_depth = np.asarray(field_depth, np.float32)
    lit = np.asarray(inputs.lit, bool)
    images = np.asarray(inputs.host_images, np.float32)
    patterns = inputs.host_patterns
    near, far = (float(x) for x in inputs.depth_range)
    with np.errstate(invalid="ignore"):
        candidate = ~lit & ~np.isfinite(depth) & (field_depth >= near) & (field_depth <= far)
    if inputs.region is not None:
        candidate &= np.asarray(inputs.region, bool)
    out = depth.copy()
    confidence = np.full(depth.shape, np.nan, np.float32)
    if not candidate.any():
        return out, confidence, candidate
    # the candidates are about 1% of the pixels: the codes and the fit are computed at those pixels only
    # (flat indices; the window means stay dense box filters)
    index = np.flatnonzero(candidate)
    uv = projector_coords_at(index, field_depth, inputs.camera, inputs.projector)
    hp, wp = patterns.shape[1:]
    inside = (uv[:, 0] >= 0) & (uv[:, 0] <= wp - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= hp - 1)
    codes = sample_patterns_at(patterns, uv)  # [N, P]
    level = (codes.mean(0) > 0.5).astype(np.float32)
    uniform = np.abs(codes - level).max(0) <= UNIFORM_TOLERANCE
    a, b = offset_and_modulation(images)
    a_near, count = (v.reshape(-1)[index] for v in _box_mean(a, lit, UNIFORM_RADIUS))
    b_near = _box_mean(b, lit, UNIFORM_RADIUS)[0].reshape(-1)[index]
    enough = count >= UNIFORM_MIN_SHARE * (2 * UNIFORM_RADIUS + 1) ** 2
    seen = images.reshape(len(images), -1)[:, index]
    fit = 1.0 - np.sqrt(np.mean((seen - a_near - b_near * codes) ** 2, axis=0)) / np.maximum(b_near, MIN_MODULATION)
    keep = inside & uniform & enough & (fit >= min_confidence)
    index, fit = index[keep], fit[keep]
    with np.errstate(invalid="ignore"):
        diff = depth - field_depth
        refined = np.isfinite(diff) & (np.abs(diff) <= UNIFORM_CORRECTION_MAX_MM)
        correction, counted = _box_mean(np.where(refined, diff, 0.0), refined, UNIFORM_CORRECTION_RADIUS)
    flat = out.reshape(-1)  # a view: writes go to out
    flat[index] = (field_depth + np.where(counted > 0, correction, 0.0)).reshape(-1)[index]
    lonely = neighbours_within(out, AGREE_MM, index) < 2  # a lone fill: no surface of its neighbours
    flat[index[lonely]] = np.nan
    index, fit = index[~lonely], fit[~lonely]
    filled = np.zeros(depth.shape, bool)
    filled.reshape(-1)[index] = True
    confidence.reshape(-1)[index] = fit
    return out, confidence, filled
