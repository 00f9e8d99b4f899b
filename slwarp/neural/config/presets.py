"""The presets: named TrainConfigs, each its options and a one-line summary of what it is for, and the preset a
run gets when it names none (`DEFAULT_PRESET`, per device type). Why each preset holds the values it does, with
the measurements, their dates and results files: docs/presets.md."""
from __future__ import annotations

from .options import ConfigError
from .switches import DEFAULT_STAGES
from .train_config import TrainConfig

__all__ = ["DEFAULT_PRESET", "PRESETS", "PRESET_SUMMARIES", "REFINE_MAX_MISFIT", "default_preset_name", "preset"]

PRESETS: dict[str, TrainConfig] = {}
PRESET_SUMMARIES: dict[str, str] = {}

# the presets' limit on the pattern model's misfit (refine_max_misfit, pattern_model.model_misfit): above it the
# refinement makes depths worse (docs/presets.md, "The shared extraction")
REFINE_MAX_MISFIT = 0.024


def _preset(name: str, summary: str, **options) -> None:
    PRESETS[name] = TrainConfig().with_options(**options)
    PRESET_SUMMARIES[name] = summary


# the extraction of tuned, fast, accurate and cpu-hashgrid; each gives its own denoising window
_DEFAULT_EXTRACTION = dict(stages=(*DEFAULT_STAGES, "search_repair", "refine", "uniform_fill", "repair_grow", "denoise"),
                           refine_range=3.0, refine_max_misfit=REFINE_MAX_MISFIT, repair_min_component=100,
                           search_doubt=True)
# the lens: a halo fitted to each scan, and where it has one (a real lens) no photometric refinement, which there
# fitted the model's errors (real captures 0-4: docs/accuracy.md, section 22)
_LENS = dict(pattern_halo="auto", refine_through_halo=False)
# the hash-grid presets through such a lens: NeuS's variance at 16x the rate and the Eikonal weight at 0.5, which
# took fast / accurate from 0.431 / 0.426 to 0.377 / 0.386 mm plate RMS over real captures 0-2 (docs/accuracy.md,
# section 23; the acceptance captures 3-4: 0.600 / 0.357 and 0.557 / 0.344) and cpu-hashgrid from 0.416 to 0.374 (run
# on GPUs; 3-4: 0.564 / 0.362 against 0.618 / 0.323); the simulator's linear camera has no halo, so they never apply
# there (where they cost accuracy: 0.099 -> 0.130 mm)
_LENS_HASHGRID = dict(lens_variance_lr_factor=16.0, lens_lambda_reg=0.5)
# the GPU presets' denoising window
_GPU_DENOISE = dict(denoise_radius=4, denoise_footprints=8.0)
# the pixels beside a depth edge settled by their codes, within 1 px: the same fields of fast / accurate, seed 0,
# every rig (4 x H200): mean MAE 1-5% / 1-3% lower, RMSE 2-7% / 2-13% lower on each rig, completeness 0.01-0.10 pt
# lower; real captures 0-2 the same plate RMS (bench/results/edge-side-cuda-*.md; docs/accuracy.md, section 26).
# cpu-hashgrid: the small rig's 8 scenes unchanged but checker (0.318 -> 0.312 mm, accuracy-cpu-edge-side.md), a
# full-resolution rods scan 0.255 -> 0.199 mm (offline, docs/accuracy.md, section 26), real captures 0-2 the same
_EDGE_SIDE = dict(edge_side_radius=1)
# the ramps the hash-grid fields draw across a step a few projector rows deep (twins of the real captures: fast 0.533 ->
# 0.478 mm, accurate 0.405 -> 0.387; the simulator's 4 rigs within 0.001 mm: docs/accuracy.md section 35)
_STEP_SPLIT = dict(step_split_radius=20)
# accurate also readmits the flying-pixel filter's edge pixels whose codes confirm them (as tuned), which the edge sides
# then settle: the same fields, seed 0, completeness 0.2-0.3 points higher on every rig, now within 0.8 points of
# GC(7)'s on each, for 0.001-0.003 mm of MAE; real captures 0-2 the same plate RMS (edge-readmit-side-cuda-seed0.md,
# edge-readmit-cuda-real.md). fast took it with the edge band, which removed the RMSE it had cost (0.02-0.09 mm)
# cpu-hashgrid drops depth pixels of photometric confidence below 0.65 (0.6 elsewhere): on the same fields of the small
# and small-vertical rigs' 8 scenes, mean MAE 0.315 / 0.274 -> 0.290 / 0.269 mm, RMSE lower, steps and rods from
# 0.73x / 0.72x / 0.71x to 0.59x / 0.59x / 0.67x GC(7), for 0.5 points of completeness (accuracy-cpu-steps-rods-
# extraction.md, -six-scenes-extraction.md); real captures 0-2 the same plate RMS, 0.5-0.9 points fewer pixels with
# depth (real-captures-cuda-cpu-default-minconf.md)
_CPU_MIN_CONFIDENCE = 0.65
# cpu-hashgrid drops a depth the repair's search contradicts below a photometric confidence of 0.9 (0.8 before, 0.7
# elsewhere): the same fields, the four small rigs' 8 scenes (2-core CPU, accuracy-cpu-doubt09.md), mean MAE 0.290 /
# 0.270 / 0.230 / 0.301 -> 0.287 / 0.264 / 0.224 / 0.291 mm, rods 0.59x / 0.67x / 0.51x / 0.74x -> 0.57x / 0.62x / 0.46x
# / 0.66x GC(7) (every scene of every small rig now at most 0.66x), no scene worse, RMSE lower, completeness 0.2-0.5
# points lower; real captures 0-2 the same plate RMS, 0.3-1.2 points fewer pixels with depth
# (real-captures-cuda-cpu-default-doubt09.md)
_CPU_DOUBT_CONFIDENCE = 0.9
# the pinholes closed (extraction.stages.HoleFill): a pixel without depth, 7 of whose 8 neighbours hold depths on one
# plane, takes the plane's depth. The same fields, seed 0, every rig (4 x H200, accuracy-cuda-hole-fill-seed0.md):
# completeness +0.17-0.24 points for fast and accurate on every rig (fast now within 1 point of GC(7) on each), MAE +0
# to +0.001 mm, RMSE within 0.003 mm; the small and small-vertical rigs' 8 scenes with cpu-hashgrid (2-core CPU,
# accuracy-cpu-hole-fill.md): +0.68 / +0.72 points, MAE 0.290 / 0.269 -> 0.290 / 0.270 mm. With 6 neighbours a thin part the
# filters dropped took its background's depth (rods: accurate 0.127 -> 0.473 mm). Real captures 0-2 with 6 (a superset
# of 7's fills): the same plate RMS (real-captures-cuda-hole-fill.md)
_HOLE_FILL = dict(hole_fill=7)
# the depths within 3 pixels of a depth edge of the field, on either side, kept only with a photometric confidence of
# 0.8 (extraction.stages.EdgeBand): an outline the field drew a pixel or two off had left them the other surface's
# depth, most of the hash-grid presets' RMSE (fast, default rig: 10-43 such pixels per smooth scene gave RMSE 0.7-1.2
# mm, 0.13-0.18 without them; gross-errors-cuda-fast.md). The same fields, seed 0, every rig (2 x H200, 2026-11-28,
# accuracy-cuda-edge-band-seed0.md): accurate's mean MAE 3-7% and RMSE 25-31% lower on each rig, completeness 0.16-0.19
# points lower; fast (with edge_readmit, which gives the completeness back) MAE 5-14% and RMSE 35-39% lower,
# completeness within 0.04 points (again on 2 x H100: accuracy-cuda-edge-band-fast-seed0.md); real captures 0-2 the
# same plate RMS (real-captures-cuda-edge-band.md)
_EDGE_BAND = dict(edge_band_radius=3, edge_band_sides="both", edge_band_confidence=0.8)
# cpu-hashgrid's band is 2 pixels wide (its small rig's pixels are twice the size): the same fields, the four small
# rigs' 8 scenes (2-core CPU, accuracy-cpu-edge-band-small.md, -rigs.md), mean MAE 0.287 / 0.264 / 0.224 / 0.291 ->
# 0.278 / 0.262 / 0.216 / 0.288 mm, RMSE 2.29 / 1.70 / 1.64 / 1.68 -> 1.90 / 1.64 / 1.35 / 1.67 mm, no scene's MAE
# worse, completeness 0.09-0.12 points lower; real captures 0-2 the same plate RMS, 0.0-0.4 points fewer pixels with
# depth (one H100, 2026-11-28, real-captures-cuda-cpu-default-edge-band.md)
_CPU_EDGE_BAND = {**_EDGE_BAND, "edge_band_radius": 2}
# fast draws half of each batch from the start's doubtful pixels (sampling.doubt_rays: lit, of fair modulation, without a
# surface-term depth, and their neighbours) during the first half of its iterations, uniformly after: its 1000 x 1024
# rays visit a pixel less than once, and outlines and steps were drawn off. Every rig, seeds 0 / 1 (one H200,
# 2026-11-28, accuracy-cuda-doubt-rays-fast-seed0.md, -seed1.md): oblique RMSE 1.203 / 1.297 -> 1.031 / 1.111 mm (GC(7)
# 1.246 / 1.226: the last simulator target fast missed), vertical and rolled lower too, default higher (0.797 / 0.912
# -> 0.981 / 0.979, GC(7) 1.093 / 1.148); mean MAE -4% to +4% per rig; completeness within 0.05 points. Drawn to the
# end, MAE rose 30-54% (the flat surfaces' rays went to the doubt). Real captures 0-2 (real-captures-cuda-doubt-rays.md):
# plate RMS 0.523 / 0.294 / 0.297 -> 0.534 / 0.305 / 0.298 mm, below the full decode's mean (0.431) and GC(7) on each
_DOUBT_RAYS = dict(doubt_rays=0.5, doubt_rays_until=0.5)
# accurate trains on 1024 rays a step instead of the paper's 2048 (2.0 million rays in all instead of 4.1 over a 1280 x
# 1024 camera's 1.3 million pixels). The simulator's 9 scenes, seed 0, one H200 (accuracy-cuda-accurate-ingredients.md:
# the default rig, both in one sweep; -rays1024-rigs.md against accuracy-cuda-nine-scenes.md): mean MAE 0.088 / 0.089 /
# 0.067 / 0.139 -> 0.084 / 0.084 / 0.063 / 0.127 mm on the default / vertical / oblique / rolled rigs, median 6-13%
# lower (most of the 10-30% by which accurate's exceeded fast's), RMSE 0.00-0.13 mm higher (still 0.40-0.72 below
# GC(7)'s), completeness 0.07-0.11 points lower; real captures 0-2 plate RMS 0.521 / 0.313 / 0.328 -> 0.506 / 0.285 /
# 0.308 mm (real-captures-cuda-accurate-rays1024.md; the acceptance captures 3-4, checked afterwards: 0.555 / 0.360 ->
# 0.602 / 0.352); the fresh command 10.8-12.1 -> 9.0-10.3 s on one H200 host (command-wall-cuda-h200-accurate-rays*.md).
# The other ways it differs from fast (two up-sampling steps, the surface term in front, the level schedule, the
# marching cubes' cells) moved none of this
_ACCURATE_RAYS = 1024
# what the hash-grid presets share
_HASHGRID = dict(field="hashgrid", lr=1e-3, lr_decay="cosine", lambda_sc=0.0, grid_table_lr_factor=10.0)

_preset("paper", "the paper's recipe, unchanged: 4000 iterations, 2048 rays, 32+32 samples, MLP 8x256, Adam 1e-4 (GPU)",
        matmul="tf32")
_preset("tuned", "paper with lr 5e-4, cosine decay, no surface-colour loss, an SDF term at the depths the codes "
        "confirm, photometric depth refinement (+-3 mm, where the pattern model fits the images), the search repair "
        "(changes in groups of >= 100 pixels, grown into the neighbours that kept another surface), the uniform-code "
        "fill, the edge readmission and the edge-aware denoising: the MLP reference, the most accurate on the real captures, "
        "minutes a scan (GPU)",
        matmul="tf32", lr=5e-4, lr_decay="cosine", lambda_sc=0.0, surface_weight=1.0, surface_after=1.0,
        edge_readmit=True, **_DEFAULT_EXTRACTION, **_LENS, **_GPU_DENOISE)
_preset("cpu", "tuned with a 4x64 field, 384 rays, 1500 iterations: minutes on two CPU cores (small rig)",
        iters=1500, rays=384, n_samples=24, n_importance=16, up_sample_steps=2, lr=5e-4, lr_decay="cosine",
        lambda_sc=0.0, hidden=64, layers=4, skip=2, n_freqs=6, search_step_mm=2.0, mc_resolution=192,
        checkpoint_every=250, log_every=25)
_preset("tiny", "a 3x48 field for 300 iterations: tests", iters=300, rays=256, n_samples=16, n_importance=8,
        up_sample_steps=1, lr=5e-4, lr_decay="cosine", sc_start=100, hidden=48, layers=3, skip=None, n_freqs=4,
        init_iters=100, search_step_mm=2.0, search_stride=3, mc_resolution=128, checkpoint_every=100, log_every=25)
_preset("fast", "hash-grid field (8 levels, 4-tap gradient), 200 + 800 iterations of 1024 rays, levels switched on "
        "quickly, two up-sampling steps, NeuS's variance at 4x the rate, half the rays on the start's doubtful pixels for "
        "half the run, with tuned's surface term (on both sides of the map) and extraction, a free-space term and the "
        "small depth steps split out of the field's ramps: a depth map as soon as possible (GPU)",
        matmul="tf32", compile=False, iters=800, init_iters=200, rays=1024, up_sample_steps=2, grid_levels=8,
        grid_gradient="finite_difference_4",
        grid_start_levels=2, grid_level_every=50, mc_resolution=256, checkpoint_every=1000, surface_weight=1.0,
        surface_after=1.0, surface_in_front=True, free_space=0.5, variance_lr_factor=4.0, edge_readmit=True,
        **_DOUBT_RAYS, **_DEFAULT_EXTRACTION, **_STEP_SPLIT, **_EDGE_SIDE, **_HOLE_FILL, **_EDGE_BAND, **_LENS,
        **_LENS_HASHGRID,
        **_GPU_DENOISE, **_HASHGRID)
_preset("accurate", "hash-grid field (8 levels, 4-tap gradient), 2000 iterations of 1024 rays, levels "
        "coarse to fine, NeuS's variance at 4x the rate, with tuned's surface term and extraction, a free-space "
        "term and the small depth steps split out of the field's ramps, through a lens with a halo NeuS's variance at 16x and the Eikonal weight at 0.5: seconds a scan, as "
        "accurate as tuned on simulated scans and as the full 40-image decode on real ones (GPU default)",
        matmul="tf32", compile=False, iters=2000, rays=_ACCURATE_RAYS, grid_levels=8, grid_gradient="finite_difference_4",
        grid_start_levels=2, grid_level_every=100, variance_lr_factor=4.0, surface_weight=1.0, surface_after=1.0, free_space=1.0,
        edge_readmit=True, **_DEFAULT_EXTRACTION, **_STEP_SPLIT, **_EDGE_SIDE, **_HOLE_FILL, **_EDGE_BAND, **_LENS,
        **_LENS_HASHGRID, **_GPU_DENOISE, **_HASHGRID)
_preset("cpu-hashgrid", "cpu with the hash-grid field (8 levels, 2^15 entries, 4-tap gradient), photometric depth "
        "refinement (+-3 mm, where the pattern model fits the images), the search repair in groups (grown), the "
        "uniform-code fill, the edge-aware denoising (5x5 windows) and the edge band (2 pixels): better MAE in less time "
        "than cpu (small rig)",
        grid_gradient="finite_difference_4", iters=1500, rays=384, n_samples=24, n_importance=16, up_sample_steps=2,
        search_step_mm=2.0, mc_resolution=192, checkpoint_every=250, log_every=25, grid_levels=8, grid_log2_table=15,
        denoise_radius=2, denoise_footprints=4.0, doubt_confidence=_CPU_DOUBT_CONFIDENCE, min_confidence=_CPU_MIN_CONFIDENCE,
        **_DEFAULT_EXTRACTION, **_EDGE_SIDE, **_HOLE_FILL, **_CPU_EDGE_BAND, **_LENS, **_LENS_HASHGRID, **_HASHGRID)

# the preset a run gets when it names none, per device type
# (GPU: the best on the real captures within 15 s in process; accurate 0.412 mm plate RMS over captures 0-4 in 8.1-8.5
# s on an H100, tuned 0.328 in minutes: docs/accuracy.md, section 23)
DEFAULT_PRESET = {"cuda": "accurate", "cpu": "cpu-hashgrid"}


def preset(name: str, **options) -> TrainConfig:
    """A copy of preset `name` with options set by flat name (see OPTIONS), validated."""
    if name not in PRESETS:
        raise ConfigError(f"unknown preset {name!r}; presets: {', '.join(PRESETS)}")
    return PRESETS[name].with_options(**options)


def default_preset_name(device) -> str:
    """The default preset of a device (a torch.device or its type as a string): DEFAULT_PRESET's entry for
    CUDA, the CPU's for any other device."""
    return DEFAULT_PRESET["cuda" if getattr(device, "type", device) == "cuda" else "cpu"]
