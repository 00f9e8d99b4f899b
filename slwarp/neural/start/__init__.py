"""The start of a training run: what the trainer starts from, from the scan, the config and the depth range.

    set_process_flags(device, config.runtime.matmul)        # torch's process-wide flags, once per trainer
    depth_range = checked_depth_range(scan, depth_range)     # ScanError without a usable one
    n_frames = frames_at_start(scan, config)                  # ScanError with fewer than two frames
    lit, volume = working_volume(scan, config, n_frames, depth_range)    # ScanError when no pixel is lit
    field = start_field(config, volume, depth_range, scan.camera)
    renderer = start_renderer(field, scan, config, n_frames, volume, depth_range, device)
    if searches(config): init_depth, info = search_start(scan, config, n_frames, depth_range, lit, images, device)
    if config.init.auto_range: depth_range, init_depth = narrowed_range(init_depth, depth_range, margin_mm)
    sigma, fit = fit_blur(scan, config, n_frames, init_depth, device)   # ScanError when it cannot be fitted
    if surface_terms_on(config.init): targets = surface_depth(init_depth, cam, prj, images, patterns, device)

The pixels lit with contrast in the frames in use give the working volume (the frustum box of those pixels between
near and far), which sizes the field; the depth search (`search`: slwarp.neural.start.search) gives the warm-up's
starting map, at whose depths the pattern blur is fitted (pattern_model.estimate_pattern_blur); the surface term pulls
the field onto the map's depths that the pixels' own codes confirm, in connected groups (`surface_depth`).
"""
from __future__ import annotations

import math

import numpy as np
import torch

from ...scans.scan import ScanError
from ..depth_maps import AGREE_MM, component_sizes
from ..fields import Volume, make_field
from ..pattern_model import (blur_patterns, estimate_pattern_blur, lit_with_contrast, offset_and_modulation,
                             photometric_confidence)
from ..render import StructuredLightRenderer
from .search import search_depth

__all__ = ["SURFACE_CONFIDENCE", "SURFACE_MIN_GROUP", "set_process_flags", "checked_depth_range", "frames_at_start",
           "working_volume", "start_field", "start_renderer", "searches", "search_start", "window_step_of",
           "narrowed_range", "fit_blur", "surface_terms_on", "surface_depth", "doubtful_pixels"]

SURFACE_CONFIDENCE = 0.8  # the surface term's depths: the map's where the pixel's own codes fit this well ...
SURFACE_MIN_GROUP = 50  # ... inside a connected group of at least this many such pixels (depth_maps.AGREE_MM apart)
# doubt rays: a doubtful pixel's modulation is at least this times the lit pixels' median. Without the bar, fast with
# doubt_rays 0.25 / 0.5 drew the checker's dark squares and its MAE rose 3x on the oblique and rolled rigs (seed 0)
DOUBT_MODULATION = 0.5


def set_process_flags(device: torch.device, matmul: str) -> None:
    """Set torch's process-wide flags for training on `device`: on the CPU flush denormal floats to zero; with
    matmul "tf32" allow TF32 in CUDA matmuls and cuDNN. They stay set for the process."""
    if device.type == "cpu":
        # transmittance products and sigmoids of a sharpening SDF underflow into denormal floats, which
        # x86 CPUs process ~100x slower (measured: 50 iterations in 46 s instead of 1.4 s)
        torch.set_flush_denormal(True)
    if matmul == "tf32":
        torch.backends.cuda.matmul.allow_tf32 = True
        torch.backends.cudnn.allow_tf32 = True


def _name(scan) -> str:
    return scan.source or "scan"


def checked_depth_range(scan, depth_range=None) -> tuple[float, float]:
    """(near, far) mm: `depth_range`, else the scan's; ScanError when neither is given or it is not 0 < near < far."""
    given = depth_range or scan.depth_range
    if given is None:
        raise ScanError(f"{_name(scan)}: no depth range in the scan: give one (near, far) in mm "
                        "(CLI: --depth-range NEAR,FAR)")
    checked = tuple(float(x) for x in given)
    if not (len(checked) == 2 and all(map(math.isfinite, checked)) and 0 < checked[0] < checked[1]):
        raise ScanError(f"{_name(scan)}: depth range {given} must be two finite numbers 0 < near < far (mm)")
    return checked


def frames_at_start(scan, config) -> int:
    """The number of the scan's frames training starts with: all, or schedule.start_frames in incremental mode;
    ScanError (naming the scan's problems) when the scan has fewer than two."""
    n_all = len(scan)
    if n_all < 2:
        raise ScanError(f"{_name(scan)}: {'; '.join(scan.problems(config.sampling.contrast_threshold))}")
    return min(config.schedule.start_frames, n_all) if config.schedule.incremental else n_all


def working_volume(scan, config, n_frames: int, depth_range) -> tuple[np.ndarray, Volume]:
    """(lit [H, W] bool: the pixels lit with contrast in the first n_frames frames, the working volume: their
    frustum box between near and far, mm); ScanError when no pixel is lit with contrast."""
    threshold = config.sampling.contrast_threshold
    lit = lit_with_contrast(offset_and_modulation(scan.images[:n_frames])[1], threshold)
    if not lit.any():
        why = scan.problems(threshold)
        raise ScanError(f"{_name(scan)}: no pixel is lit with contrast (modulation above {threshold}) in the frames "
                        "used" + (f": {'; '.join(why)}" if why else ""))
    return lit, Volume.from_frustum(scan.camera, lit, depth_range)


def start_field(config, volume: Volume, depth_range, camera) -> torch.nn.Module:
    """The config's field (fields.make_field) sized by the working volume; a hash grid's finest cells from the
    camera's pixel footprint at the middle of the depth range (mm)."""
    pixel_mm = 0.5 * sum(depth_range) / (0.5 * (camera.fx + camera.fy))
    return make_field(config.field, volume, init="camera" if config.init.method == "camera" else "sphere",
                      far=depth_range[1], pixel_mm=pixel_mm)


def start_renderer(field: torch.nn.Module, scan, config, n_frames: int, volume: Volume, depth_range,
                   device: torch.device) -> StructuredLightRenderer:
    """The renderer of the first n_frames frames around `field`, as the config samples (a fitted pattern blur
    starts at 0: `fit_blur` sets it)."""
    s = config.sampling
    return StructuredLightRenderer(
        field, scan.camera, scan.projector, scan.patterns[:n_frames], scan.images[:n_frames], depth_range=depth_range,
        volume=volume, n_samples=s.n_samples, n_importance=s.n_importance, up_sample_steps=s.up_sample_steps,
        contrast_threshold=s.contrast_threshold, backend=config.runtime.backend, device=device,
        compile_field=config.runtime.compile and device.type == "cuda",
        pattern_blur=0.0 if s.pattern_blur == "auto" else float(s.pattern_blur))


def searches(config) -> bool:
    """Whether a new run (no starting map given) starts from the depth search: init.method "search" with a warm-up."""
    return config.init.method == "search" and config.init.iters > 0


def search_start(scan, config, n_frames: int, depth_range, lit: np.ndarray, images, device: torch.device):
    """(starting depth map [H, W] mm, NaN: none; the search's info dict): the depth search (search.search_depth) on
    the lit pixels, the patterns blurred by the fixed pattern_blur (1 px when it is fitted). images [N, H, W]: the
    frames as the pattern model holds them (training.pattern_model_inputs: on a GPU the renderer's tensors)."""
    blur = 1.0 if config.sampling.pattern_blur == "auto" else float(config.sampling.pattern_blur)
    # on a GPU the search reads the frames where they are: the renderer's images, the patterns blurred there
    patterns = blur_patterns(torch.as_tensor(scan.patterns[:n_frames], device=device), blur)
    if device.type != "cuda":
        patterns = patterns.numpy()
    return search_depth(scan.camera, scan.projector, images, patterns, depth_range, valid=lit,
                        step_mm=config.init.search_step_mm, stride=config.init.search_stride,
                        window_step=window_step_of(scan, config, n_frames), device=device)


def window_step_of(scan, config, n_frames: int) -> int:
    """The depth search's window step (camera px): config.init.search_window_step, or where that is 0 (auto) the
    largest window_step in the roles of the scan's first n_frames frames (a set made by design-patterns
    --window-step S declares S), else 1."""
    if config.init.search_window_step > 0:
        return int(config.init.search_window_step)
    steps = [r.window_step for r in scan.roles[:n_frames] if r is not None and r.window_step is not None]
    return max(steps, default=1)


# auto_range narrows the depth range only where the searched depths fill less than this share of it: a range a user
# set loosely around the scene (real captures 0-2: 800-2600 mm for a plate and a wall at 1.1-1.65 m, 37% after
# narrowing), not one already close around it (the virtual scanner: 450-1100 mm for 0.63-1.01 m, 74%)
NARROW_BELOW = 0.6
NARROW_PERCENTILES = (0.1, 99.9)


def narrowed_range(depth_map: np.ndarray, depth_range, margin_mm: float) -> tuple[tuple[float, float], np.ndarray]:
    """((near, far) mm, the map with depths outside it set to NaN): depth_range narrowed to the map's depths (their
    0.1st-99.9th percentiles) plus a margin (margin_mm, at least 5% of their span), when that is less than
    NARROW_BELOW of the given range; else depth_range and the map unchanged. depth_map [H, W] mm, NaN: none.
    Why: NeuS samples each ray between near and far, and the hash grid's cells span the working volume; a range three
    times wider than the scene spreads both thin (real captures: `fast` on capture 1, 0.549 -> 0.385 mm plate RMS
    at 1000-1800 mm instead of 800-2600, bench/results/real-captures-cuda-range-*.md)."""
    near, far = (float(x) for x in depth_range)
    d = np.asarray(depth_map)[np.isfinite(depth_map)]
    if d.size < 100:
        return (near, far), depth_map
    lo, hi = np.percentile(d, NARROW_PERCENTILES)
    margin = max(float(margin_mm), 0.05 * float(hi - lo))
    new_near, new_far = max(near, float(lo) - margin), min(far, float(hi) + margin)
    if new_far - new_near >= NARROW_BELOW * (far - near):
        return (near, far), depth_map
    with np.errstate(invalid="ignore"):
        inside = (depth_map >= new_near) & (depth_map <= new_far)
    return (new_near, new_far), np.where(inside, depth_map, np.nan).astype(np.asarray(depth_map).dtype)


def fit_blur(scan, config, n_frames: int, init_depth, device: torch.device) -> tuple[float, dict | None]:
    """(pattern blur sigma in projector px, the fit's error per sigma or None): fitted at the starting map's depths
    init_depth [H, W] mm (pattern_model.estimate_pattern_blur); 1 px without a map. ScanError when too few pixels
    have a starting depth (the scan does not fit its model), naming the scan's problems."""
    if init_depth is None:
        return 1.0, None
    cam = scan.camera
    try:
        sigma, fit = estimate_pattern_blur(cam, scan.projector, scan.images[:n_frames], scan.patterns[:n_frames],
                                           np.asarray(init_depth, np.float32).reshape(cam.height, cam.width),
                                           device=device)
    except ValueError as e:
        why = scan.problems(config.sampling.contrast_threshold)
        raise ScanError(f"{_name(scan)}: " + (f"{'; '.join(why)} (so the pattern blur cannot be fitted: {e})" if why
                        else f"cannot fit the pattern blur ({e}); check the depth range and the patterns, or give a "
                        "fixed pattern_blur (--pattern-blur)")) from None
    return sigma, fit


def surface_terms_on(init) -> bool:
    """Whether the surface or free-space term is on (init: an InitConfig), i.e. they need `surface_depth`."""
    return init.surface_weight > 0 or init.surface_after > 0 or init.free_space > 0


def doubtful_pixels(confirmed: torch.Tensor, lit: torch.Tensor, modulation: torch.Tensor, radius: int) -> torch.Tensor:
    """[H, W] bool: the lit pixels ([H, W] bool) of fair modulation (at least DOUBT_MODULATION times the lit pixels'
    median; modulation [H, W], the images' b) without a confirmed depth (confirmed [H, W] mm, NaN: none; the surface
    term's targets), and the lit pixels within `radius` pixels (Chebyshev) of one. Where the depth search doubts lie
    the outlines and thin parts (docs/accuracy.md, section 33); dark albedo is doubted for its noise, which more rays
    do not lift (the checker's dark squares)."""
    lit = lit.to(torch.bool)
    b = modulation.to(lit.device)
    fair = b >= DOUBT_MODULATION * b[lit].median() if lit.any() else lit
    doubt = (lit & fair & ~torch.isfinite(confirmed.to(lit.device))).float()
    if radius > 0:
        doubt = torch.nn.functional.max_pool2d(doubt[None, None], 2 * radius + 1, stride=1, padding=radius)[0, 0]
    return lit & (doubt > 0)


def surface_depth(init_depth: torch.Tensor, camera, projector, images, patterns, device) -> torch.Tensor:
    """[H*W] (mm, NaN: none; on `device`) the starting map init_depth [H*W] (mm)'s depths that the surface term pulls
    the field onto: those that their own pixel's codes confirm (photometric confidence >= SURFACE_CONFIDENCE, images and
    patterns as training.pattern_model_inputs gives them) inside a connected group of at least SURFACE_MIN_GROUP
    of them (8 neighbours, each within AGREE_MM of the next). Why: its gradient does not vanish far from the
    field's surface, so a wrong depth of the map raises a wrong surface. A 5x5 window's foreground depth
    spread over the background beside a depth edge fits the pixel's own codes poorly; a chance match of the
    codes may fit them well but comes in small scattered groups (rolled-rig spheres: 3224 targets more than
    20 mm in front of the truth, down to the near plane, raised floaters; none lies in a group of 50)."""
    d = init_depth.reshape(camera.height, camera.width).cpu().numpy()
    conf = photometric_confidence(d, camera, projector, images, patterns)
    kept = np.where(conf >= SURFACE_CONFIDENCE, d, np.nan).astype(np.float32)
    kept[component_sizes(kept, AGREE_MM) < SURFACE_MIN_GROUP] = np.nan
    return torch.as_tensor(kept.reshape(-1), device=device)
