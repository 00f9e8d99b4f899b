"""The six sections of a TrainConfig, one dataclass each, and the registry of their options by flat name
(`OPTIONS`, `RESUMABLE`; `REMOVED_OPTIONS`: what configs of earlier versions may still hold)."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal

from .options import ConfigError, Option, StageList, collect_options, option
from .switches import DEFAULT_STAGES

__all__ = ["CONTRAST_THRESHOLD", "DOUBT_CONFIDENCE", "ExtractionConfig", "FieldConfig", "InitConfig", "OPTIONS",
           "REMOVED_OPTIONS", "RESUMABLE", "RuntimeConfig", "SECTIONS", "SamplingConfig", "ScheduleConfig", "option_named"]

# minimum modulation b (full-scale units, images in [0, 1]) of a pixel lit with usable contrast: the default of
# contrast_threshold and of the pattern model's contrast test (slwarp.neural.pattern_model.lit_with_contrast)
CONTRAST_THRESHOLD = 0.05
# the search repair's doubt rule (extraction.repair): a depth a per-pixel search contradicts is dropped when its
# photometric confidence is below this; the default of doubt_confidence. 0.7 against none: small rig, cpu-hashgrid,
# rods 1.392 -> 1.066 mm, steps 0.646 -> 0.560, bunny and torus -0.001, completeness -0.2 to -0.3 pt
DOUBT_CONFIDENCE = 0.7


@dataclass
class FieldConfig:
    """The SDF network: `kind` picks it, and only that kind's options apply.

    mlp: NeuS's MLP (positional encoding, Softplus(beta=100), weight normalisation, geometric initialisation);
    the paper's field. hashgrid: `HashGridSDF` (slwarp.neural.fields.hashgrid), a multiresolution hash encoding and
    a small MLP, trained with its own Adam groups (tables at grid_table_lr_factor x lr) and levels switched on
    coarse to fine (grid_start_levels after the warm-up, one more every grid_level_every iterations)."""

    kind: Literal["mlp", "hashgrid"] = option("mlp", "the SDF network: mlp (NeuS's MLP, the paper's) or hashgrid "
                                              "(multiresolution hash grid + small MLP)", name="field")
    hidden: int = option(256, "width of the field MLP's hidden layers", min=1)
    layers: int = option(8, "hidden layers of the field MLP", min=1)
    skip: int | None = option(4, "hidden layer that re-receives the encoded input (none: no skip; below layers)", min=1)
    n_freqs: int = option(6, "positional-encoding frequencies (0: raw coordinates)", min=0)
    grid_levels: int = option(16, "hash grid: resolution levels", min=1, max=64)
    grid_log2_table: int = option(19, "hash grid: log2 of the entries of a hashed level's table", min=4, max=26)
    grid_base: int = option(16, "hash grid: cells per side of the coarsest level", min=1)
    # "auto": the power of two nearest to the volume's largest side over the pixel footprint at the middle of
    # the depth range (finer failed on the small rig: docs/hashgrid.md): 2048 on the default rig, 512 on the small
    grid_finest: int | Literal["auto"] = option("auto", "hash grid: cells per side of the finest level, or auto (the "
                                                "camera's pixel footprint at the working depth)", min=1, max=65536)
    grid_hidden: int = option(64, "hash grid: width of its MLP's hidden layers", min=1)
    grid_layers: int = option(1, "hash grid: hidden layers of its MLP", min=1)
    grid_activation: Literal["softplus", "relu"] = option("softplus", "hash grid: MLP activation (softplus: beta 100)")
    grid_gradient: Literal["finite_difference", "finite_difference_4", "analytic"] = option(
        "finite_difference", "hash grid: spatial gradient for the Eikonal term and normals (finite_difference: "
        "tetrahedral taps one finest active cell apart; finite_difference_4: the same taps give the value too, as "
        "their mean; analytic: exact, faster, lets thin sheets survive on cell faces)")
    grid_table_lr_factor: float = option(10.0, "hash grid: the tables' Adam learning rate as a multiple of lr",
                                         above=0.0)
    grid_start_levels: int = option(2, "hash grid: levels switched on at the start (and in the warm-up)", min=1)
    grid_level_every: int = option(150, "hash grid: iterations after the warm-up between two added levels "
                                   "(0: all levels from the end of the warm-up on)", min=0)

    def network(self) -> dict:
        """The kind and the options of that kind: what defines the network (a checkpoint must match it)."""
        keys = ("hidden", "layers", "skip", "n_freqs") if self.kind == "mlp" else tuple(
            f.name for f in dataclasses.fields(self) if f.name.startswith("grid_"))
        return {"kind": self.kind, **{k: getattr(self, k) for k in keys}}


@dataclass
class SamplingConfig:
    """What one training step renders."""

    rays: int = option(2048, "rays (camera pixels) per iteration", min=1)
    n_samples: int = option(32, "coarse samples per ray", min=1)
    n_importance: int = option(32, "NeuS up-sampled samples per ray (a multiple of up_sample_steps)", min=0)
    up_sample_steps: int = option(4, "NeuS up-sampling steps", min=0)
    contrast_threshold: float = option(CONTRAST_THRESHOLD, "minimum modulation b (full scale) of a pixel the losses use",
                                       min=0.0, max=1.0)
    # the camera sees the projected pattern blurred (projector defocus, the pixel's footprint): the renderer
    # samples it blurred too; "auto" fits the sigma to the images at the depth-search map (1.0 px without one)
    pattern_blur: float | Literal["auto"] = option("auto", "Gaussian blur of the patterns as rendered, projector px, or "
                                                   "auto (fitted to the images at the depth-search map)", min=0.0)

    # a lens's halo: on the real captures about 10% of the light spread over about 40 projector px around every edge
    # (bench/results/edge-profile-cpu.md); the simulator's cameras have none. "auto" fits the share to the images
    # at the depth-search map (pattern_model.fit_halo: 0 unless a halo explains them better)
    pattern_halo: float | Literal["auto"] = option(0.0, "share of the projected light the model spreads into a wide "
                                                   "halo around the patterns (pattern_model.with_halo; 0: none), or "
                                                   "auto (fitted to the images at the depth-search map)",
                                                   min=0.0, max=0.5)
    pattern_halo_sigma: float = option(40.0, "the halo's Gaussian sigma, projector px", above=0.0)
    # the start's doubtful pixels are where the field goes wrong (outlines, thin parts: fast's oblique rods lost whole
    # stretches), and a uniform draw visits each pixel less than once in fast's 1000 x 1024 rays
    doubt_rays: float = option(0.0, "share of each batch's rays drawn from the lit pixels of fair modulation the start "
                               "leaves without a surface-term depth (without the search's depth when that term is "
                               "off: the doubtful pixels, outlines and thin parts) and their neighbours within "
                               "doubt_rays_radius; the rest from every lit pixel (0: uniform)", min=0.0, max=0.9)
    doubt_rays_radius: int = option(1, "doubt rays: pixels within this many pixels of a doubtful one are drawn with "
                                    "it", min=0)
    doubt_rays_until: float = option(1.0, "doubt rays: drawn during this fraction of the iterations (the warm-up "
                                     "included), uniform draws after it", above=0.0, max=1.0)


@dataclass
class ScheduleConfig:
    """Iterations, learning rate, loss weights, incremental mode."""

    # resumable: more iterations continue a run (with cosine decay, the decay stretches to the new total)
    iters: int = option(4000, "training iterations (after the warm-up)", min=1, resumable=True)
    lr: float = option(1e-4, "Adam learning rate", above=0.0)
    lr_decay: Literal["none", "cosine"] = option("none", "learning-rate schedule: none (paper: constant) or cosine "
                                                 "(NeuS: decay to lr_final x lr)")
    lr_final: float = option(0.05, "cosine decay: the final learning rate as a fraction of lr", min=0.0, max=1.0)
    # NeuS's variance v (inv_s = exp(10 v)) moves by about Adam's step per iteration at most, so lr x iterations bound
    # how sharp the rendering may get: a short schedule may need it faster than the field
    variance_lr_factor: float = option(1.0, "Adam learning rate of NeuS's variance as a multiple of lr", above=0.0)
    # Adam's bias correction counts steps from a parameter's first step; a hash-grid level switched on at iteration
    # t takes its first steps with the correction of step t, about 2-4x the table's rate for tens of steps. Off in
    # every preset: per-level counts cost `accurate` 3-8% MAE on the simulator, and `fast` 0.378 -> 0.391 mm plate
    # RMS on real captures 0-2, for a lower RMSE of `fast` on the simulator (bench/results/level-adam-steps-cuda.md)
    level_adam_steps: bool = option(False, "hash grid: Adam counts each level's steps from the iteration it is "
                                    "switched on (its own bias correction) instead of from the first step")
    lambda_rc: float = option(1.0, "weight of the rendered-colour loss L_rc (0 only for the loss ablation)", min=0.0)
    lambda_sc: float = option(1.0, "weight of the surface-colour loss L_sc, from sc_start on", min=0.0)
    sc_start: int = option(1000, "iteration where L_sc starts", min=0)
    lambda_reg: float = option(0.1, "weight of the Eikonal loss L_reg", min=0.0)
    # a scan whose lens has a halo (the fitted or given pattern_halo above 0: a real lens) is one the pattern model
    # explains only approximately: there the hash-grid presets train with a sharper variance schedule and a
    # stronger Eikonal prior (real captures 0-2: docs/accuracy.md, section 23); scans without a halo keep the above
    lens_variance_lr_factor: float | None = option(None, "NeuS's variance rate (x lr) instead of variance_lr_factor "
                                                   "where the scan's lens has a halo (pattern_halo fitted or given "
                                                   "above 0; none: variance_lr_factor)", above=0.0)
    lens_lambda_reg: float | None = option(None, "the Eikonal weight instead of lambda_reg where the scan's lens has "
                                           "a halo (none: lambda_reg)", min=0.0)
    anneal_end: int = option(0, "NeuS cos-anneal over this many iterations (0: none)", min=0)
    incremental: bool = option(False, "start with start_frames frames and add one every add_every iterations")
    start_frames: int = option(3, "incremental: frames at the start", min=1)
    add_every: int = option(500, "incremental: iterations between added frames", min=1)


@dataclass
class InitConfig:
    """Where the field starts.

    The photometric loss is far from convex in depth: NeuS's sphere leaves surfaces hundreds of mm off in
    other minima (232 mm MAE on the small-rig bunny), so by default a depth search gives a starting map that a
    warm-up pulls the rendered depth onto."""

    method: Literal["search", "sphere", "camera"] = option(
        "search", "search: depth-search map + warm-up; sphere: NeuS's geometric initialisation (the paper); "
        "camera: a surface at the far depth around the camera", name="init")
    iters: int = option(300, "warm-up iterations pulling the rendered depth onto the initial depth map", min=0,
                        name="init_iters")
    surface_weight: float = option(0.0, "warm-up: weight of an SDF term at the initial map's points that the "
                                   "pixel's codes confirm (SDF 0 there, >= 0 surface_band_mm in front along the ray, "
                                   "<= 0 behind); its gradient does not vanish where the field has no surface yet, "
                                   "as the rendered depth's does (a thin part in front of the background; 0: off)",
                                   min=0.0)
    surface_after: float = option(0.0, "after the warm-up: weight of the same SDF term, only at pixels where the "
                                  "field's rendered depth is more than 5 mm behind the initial map's (a thin part in "
                                  "front that training lost; 0: off)", min=0.0)
    surface_in_front: bool = option(False, "after the warm-up the surface term (at surface_after) also acts where the "
                                    "field's rendered depth is more than 5 mm in front of the initial map's confirmed "
                                    "depth, not only behind it (a step's edge the field carried over the lower step)")
    free_space: float = option(0.0, "after the warm-up: weight of a free-space term at pixels where the field's "
                               "rendered depth is more than 5 mm in front of the initial map's confirmed depth (a gap "
                               "or background the field bridged): relu(-SDF) summed over the ray's samples more than "
                               "5 mm before the map's point (0: off)", min=0.0)
    surface_band_mm: float = option(0.5, "surface term: the distance (mm) along the ray of its points in "
                                    "front of and behind the initial map's point", above=0.0)
    auto_range: bool = option(False, "after the depth search, narrow the depth range to the searched depths (0.1st-"
                              "99.9th percentiles) plus auto_range_margin_mm when that is under 0.6 of the range given: "
                              "ray samples and hash-grid cells where the scene is (start.narrowed_range)")
    auto_range_margin_mm: float = option(50.0, "auto_range: the margin (mm) before and beyond the searched depths "
                                         "(at least 0.05 of their span)", min=0.0)
    search_step_mm: float = option(1.0, "depth-search hypothesis spacing (mm)", above=0.0)
    search_stride: int = option(2, "depth search on every stride-th pixel", min=1)
    search_window_step: int = option(0, "depth search: camera px between its windows' pixels; 0: the step the scan's "
                                     "designed set was made for (its roles' window_step, design-patterns "
                                     "--window-step S), else 1 (adjacent pixels)", min=0)


@dataclass
class RuntimeConfig:
    """How and where the run executes (none of it changes the method)."""

    seed: int = option(0, "random seed (field initialisation, pixel batches, ray jitter)", min=0)
    # backend, device, compile and cuda_graph run the same computation (equal to float rounding, not bit for
    # bit): a run may continue on another device or backend; matmul changes the precision, so it stays
    backend: Literal["warp", "torch"] = option("warp", "fused Warp kernels or their pure-torch twin", resumable=True)
    device: str = option("auto", "auto (CUDA when present), cpu, cuda or cuda:N", resumable=True)
    matmul: Literal["fp32", "tf32"] = option("fp32", "CUDA matrix precision of the field MLP")
    compile: bool = option(True, "torch.compile the field (CUDA only)", resumable=True)
    # the whole step (render, losses, backward, Adam) captured once and replayed: no Python, launch or
    # allocation cost per step; the same draws and results as plain launches; falls back (with a warning)
    # to plain launches if the capture fails
    cuda_graph: bool = option(True, "CUDA: capture the training step once as a CUDA graph and replay it", resumable=True)
    checkpoint_every: int = option(500, "iterations between checkpoints", min=1, resumable=True)
    log_every: int = option(50, "iterations between logged losses", min=1, resumable=True)
    retry_lost_surface: bool = option(True, "train once more, with the next seed, where the field lost the surface "
                                      "(most lit pixels without a depth in range where the depth search found one)",
                                      resumable=True)



@dataclass
class ExtractionConfig:
    """From the trained field to a depth map.

    `stages` lists what runs, in order (slwarp.neural.extraction: each stage reads its own options below); the
    options of STAGE_SWITCHES add or remove their stage. Every extraction option acts after training: a resumed run
    may change it (e.g. extract again at another resolution)."""

    stages: tuple[str, ...] = option(StageList(DEFAULT_STAGES), "the extraction's stages in the order they run, "
                                     "comma-separated (slwarp.neural.extraction.STAGES); edge_filter, search_repair, "
                                     "search_doubt, refine_range, uniform_fill, repair_grow, step_split_radius, "
                                     "edge_side_radius, denoise_radius, hole_fill and edge_band_radius add or remove "
                                     "theirs", resumable=True)
    # below 16 cells a cell spans more than 1/16 of the working volume: no scene's surface survives it
    mc_resolution: int = option(384, "marching-cubes cells along the volume's longest side", min=16, resumable=True)
    depth_method: Literal["mesh", "sphere"] = option("mesh", "depth by ray casting the marching-cubes mesh, or by "
                                                     "sphere tracing the field", resumable=True)
    edge_filter: float = option(10.0, "drop depth-edge (flying) pixels: jumps above this many pixel footprints (0: off)",
                                min=0.0, resumable=True)
    edge_readmit: bool = option(False, "give back the depth-edge pixels that lie on one side of the edge: enough "
                                "neighbours the filter kept within its limit (edge_readmit_support) and a photometric "
                                "confidence of at least edge_readmit_confidence (needs edge_filter > 0)", resumable=True)
    edge_readmit_support: int = option(3, "edge readmission: neighbours (of 8) the filter kept within its limit of the "
                                       "pixel's depth", min=1, max=8, resumable=True)
    edge_readmit_confidence: float = option(0.9, "edge readmission: the pixel's photometric confidence at least this",
                                            min=0.0, max=1.0, resumable=True)
    # what the method knows about each pixel, as a map in [0, 1] written beside the depth (slwarp.neural.extraction.confidence);
    # photometric with min_confidence 0.6 is the photometric check (relative RMS residual below 0.4)
    confidence: Literal["photometric", "peak", "agreement", "uniqueness", "combined"] = option(
        "photometric", "per-pixel confidence written as confidence.npy and used by min_confidence: photometric (1 - "
        "relative RMS residual of the codes), peak (NeuS weight on the surface), agreement (rendered vs extracted "
        "depth), uniqueness (no other depth on the ray fits the codes), combined (photometric x peak: ranks errors best)",
        resumable=True)
    min_confidence: float = option(0.6, "drop depth pixels whose confidence is below this (0: keep all)", min=0.0,
                                   max=1.0, resumable=True)
    search_repair: bool = option(False, "a per-pixel depth search (3x3 and 5x5 windows) fills the lit pixels left "
                                 "without depth and replaces depths it clearly contradicts (thin parts the field "
                                 "missed), judged by the photometric confidence", resumable=True)
    repair_min_component: int = option(0, "search repair: keep a fill or replacement only in a connected group of at "
                                       "least this many changed pixels of one surface, counted as on a 1280x1024 camera "
                                       "(fewer on a smaller image, in proportion to its pixel count, down to 10; 0: "
                                       "two agreeing neighbours suffice)", min=0, resumable=True)
    repair_grow: bool = option(False, "search repair: at the end, spread its changes to neighbouring pixels that kept "
                               "another surface's depth (over 20 mm off) where the codes fit the repaired surface "
                               "better; drops and fills nothing (needs search_repair)", resumable=True)
    search_doubt: bool = option(False, "drop depths that a per-pixel depth search (3x3 window) contradicts by more "
                                "than 6 mm and whose photometric confidence is below doubt_confidence (the "
                                "background's depth on a thin part); fills and replaces nothing (search_repair "
                                "includes it)", resumable=True)
    # 0.8 with cpu-hashgrid, the same fields: mean MAE on the 4 small rigs 0.360 / 0.295 / 0.296 / 0.330 -> 0.330 /
    # 0.278 / 0.287 / 0.319 mm (rods 0.831 -> 0.645 on the small rig), no scene worse, completeness -0.2 pt each
    # (bench/results/accuracy-cpu-doubt-confidence*.md); real captures 0-2 the same plate RMS (doubt-confidence-cuda-
    # real.md, edge-side-cuda-real.md): cpu-hashgrid took 0.8, and later 0.9 (config.presets). fast and accurate keep
    # 0.7: 2-4% of MAE for 0.2 pt of the completeness they are short of (doubt-confidence-cuda-seed0.md)
    doubt_confidence: float = option(DOUBT_CONFIDENCE, "search repair and search_doubt: a depth the search "
                                     "contradicts is dropped when its photometric confidence is below this",
                                     min=0.0, max=1.0, resumable=True)
    uniform_fill: bool = option(False, "after the refinement, lit pixels without contrast (a projector square black or "
                                "white in every pattern) take the field's depth where the codes it predicts there "
                                "are uniform and explain the images with the neighbours' offset and modulation",
                                resumable=True)
    refine_range: float = option(0.0, "photometric refinement after the filters: each pixel's depth moves by the offset "
                                 "within +- this many mm that best explains its 7x7 window's images (offset and "
                                 "modulation by least squares, blur per projector depth; 0: off)", min=0.0,
                                 resumable=True)
    refine_check: bool = option(False, "keep the refinement only if it explains frames it did not see better: each "
                                "frame held out in turn, the others refine, the held-out frame's residual must fall "
                                "on average. For real captures: there it undid a refinement that doubled the plate's "
                                "RMS; on simulated full-resolution scans it also undid helpful ones (4 of 8), so off "
                                "by default", resumable=True)
    refine_through_halo: bool = option(True, "refine also where the pattern model has a lens halo (pattern_halo above "
                                       "0, fitted or given: a real lens, whose optics the model only approximates; on "
                                       "real captures 0-4 the held-out check refused every such refinement)",
                                       resumable=True)
    refine_max_misfit: float = option(0.0, "refine only where the pattern model fits: skip the refinement when the "
                                      "median relative misfit of the lit pixels at the depth before refinement is above "
                                      "this (simulated scans 0.015-0.022, the real capture 0.026; 0: always refine)",
                                      min=0.0, resumable=True)
    step_split_radius: int = option(0, "after the repair and the fill: a pixel between two surfaces along an image "
                                    "axis (lines fitted to the depths this many to this + 16 pixels away on each side "
                                    "disagree at it by more than edge_filter footprints) takes the side line whose "
                                    "codes fit its window best: the ramps a smooth field draws across a small depth "
                                    "step (0: off)", min=0, resumable=True)
    step_split_margin: float = option(0.9, "step split: a side line is taken when its window's code residual is at "
                                      "most this times that of the map's own depths", above=0.0, max=1.0,
                                      resumable=True)
    edge_side_radius: int = option(0, "after the repair and the fill: each pixel with a depth across a depth edge "
                                   "(a jump above edge_filter footprints) within this many pixels keeps its depth, "
                                   "takes the one across or is dropped, as its codes fit them (0: off)", min=0,
                                   resumable=True)
    edge_side_margin: float = option(0.5, "edge sides: a depth is kept or taken when its code residual is at most "
                                     "this times the other's; between the two the pixel is dropped", above=0.0,
                                     max=1.0, resumable=True)
    denoise_radius: int = option(0, "last: each depth becomes the value at its pixel of a plane fitted (least squares "
                                 "in pixel coordinates) to the depths of its (2r + 1)^2 window that lie within "
                                 "denoise_footprints pixel footprints of its own (0: off)", min=0, resumable=True)
    denoise_footprints: float = option(4.0, "denoising: a window's depth takes part in the plane fit when within this "
                                       "many pixel footprints (z / f mm each) of the centre's depth", above=0.0,
                                       resumable=True)
    hole_fill: int = option(0, "after the denoising: a pixel without depth (lit with contrast) at least this many of "
                            "whose 8 neighbours have depths on one plane takes the plane's depth there (0: off)", min=0,
                            max=8, resumable=True)
    hole_fill_footprints: float = option(0.5, "hole fill: every neighbour within this many pixel footprints (z / f mm "
                                         "each) of the fitted plane", above=0.0, resumable=True)
    edge_band_radius: int = option(0, "last: a depth within this many pixels of a depth edge of the field (a jump "
                                   "above edge_filter footprints; behind it, or on either side: edge_band_sides) is "
                                   "kept only with a confidence of at least edge_band_confidence: an outline the field "
                                   "drew a pixel or two off leaves those pixels with the other surface's depth (0: off)",
                                   min=0, resumable=True)
    edge_band_confidence: float = option(0.8, "edge band: the confidence a depth near a depth edge must reach", min=0.0,
                                         max=1.0, resumable=True)
    edge_band_sides: Literal["far", "both"] = option("both", "edge band: the pixels on either side of an edge (both) "
                                                     "or only behind it (far)", resumable=True)
    edge_band_far_radius: int = option(0, "edge band: behind an edge, the band's width in pixels (0: edge_band_radius)",
                                       min=0, resumable=True)
    edge_band_far_confidence: float = option(0.0, "edge band: behind an edge, the confidence a depth must reach (0: "
                                             "edge_band_confidence)", min=0.0, max=1.0, resumable=True)


SECTIONS = {"field": FieldConfig, "sampling": SamplingConfig, "schedule": ScheduleConfig, "init": InitConfig,
            "runtime": RuntimeConfig, "extraction": ExtractionConfig}


OPTIONS: dict[str, Option] = collect_options(SECTIONS)
# options that configs saved by earlier versions may still hold: read past (with a warning when set), so that an
# old run's config.yaml or checkpoint still loads; {(section, key): why it went}
REMOVED_OPTIONS: dict[tuple[str, str], str] = {
    ("extraction", "search_confirm"): "it gave dropped pixels back at +0.003 to +0.05 mm of MAE on every GPU scan "
                                      "measured; edge_readmit does the same job better (docs/accuracy.md, sections "
                                      "10 and 16)",
}
# the options a resumed run may change (flat names); every other one is part of the run's identity
RESUMABLE: tuple[str, ...] = tuple(name for name, opt in OPTIONS.items() if opt.resumable)


def option_named(name: str) -> Option:
    """The option of flat name `name`; ConfigError listing the options when there is none."""
    opt = OPTIONS.get(name)
    if opt is None:
        raise ConfigError(f"unknown option {name!r}; options: {', '.join(OPTIONS)}")
    return opt
