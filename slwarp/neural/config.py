"""TrainConfig: everything that defines a neural reconstruction run, in six typed sections.

    field       the SDF network: kind mlp (NeuS's MLP: width, depth, skip, encoding) or hashgrid (its grid_* options)
    sampling    what a training step renders: rays, samples per ray, pixels with contrast, pattern blur
    schedule    iterations, Adam's learning rate and its decay, loss weights, incremental mode
    init        where the field starts: depth-search map + warm-up, NeuS's sphere, or a far surface
    runtime     how and where it runs (seed, backend, device, precision, compile, CUDA graph, logs)
    extraction  from the trained field to a depth map (marching cubes, ray casting, filters)

Every option has one flat name, unique across sections (`OPTIONS`): the CLI flag (--name with dashes, generated
from this module with its type, choices and help), the keyword of `preset(name, **options)` and
`TrainConfig.with_options`, and the key of bench specs (key=value). On disk a config is YAML with the sections
as mappings (`load_config`, `save_config`). `TrainConfig.validate` checks every value against its type and
range and raises ConfigError naming the option, the value and what is allowed.

Resuming: a run's checkpoint records its `fixed_options()` (every option but the resumable ones) and a resumed run
must keep them; the options marked `resumable` (`RESUMABLE`: more iterations, logging and checkpoint intervals,
where and how the same computation runs, and the whole extraction section, which acts after training) may change.

PRESETS: paper (the paper's recipe, unchanged), tuned, fast and accurate (the hash-grid field, GPU), cpu and
cpu-hashgrid (small rig, two CPU cores), tiny (tests); `PRESET_SUMMARIES` says what each is for.
`default_preset_name(device)` reads DEFAULT_PRESET (one entry per device type).
"""
from __future__ import annotations

import dataclasses
import math
import typing
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from ..devices import DEVICE_PATTERN
from .pattern_model import CONTRAST_THRESHOLD, REFINE_MAX_MISFIT

__all__ = [
    "ConfigError",
    "FieldConfig",
    "SamplingConfig",
    "ScheduleConfig",
    "InitConfig",
    "RuntimeConfig",
    "ExtractionConfig",
    "TrainConfig",
    "Option",
    "OPTIONS",
    "RESUMABLE",
    "SECTIONS",
    "PRESETS",
    "PRESET_SUMMARIES",
    "preset",
    "parse_assignments",
    "default_preset_name",
    "DEFAULT_PRESET",
    "load_config",
    "save_config",
]


class ConfigError(ValueError):
    """An unknown option or a value an option cannot take; the message names the option, the value and
    what is allowed."""


def option(default, help: str, *, min=None, max=None, above=None, name: str | None = None, resumable: bool = False):
    """A config field: its default, a one-line help (CLI --help and docs), the allowed range (min <= value <=
    max, value > above), its flat name when it differs from the field's (it must be unique across sections) and
    whether a resumed run may change it (`resumable`: it does not define what the run computes)."""
    return dataclasses.field(default=default, metadata={"help": help, "min": min, "max": max, "above": above, "name": name,
                                                        "resumable": resumable})


@dataclass
class FieldConfig:
    """The SDF network: `kind` picks it, and only that kind's options apply.

    mlp: NeuS's MLP (positional encoding, Softplus(beta=100), weight normalisation, geometric initialisation);
    the paper's field. hashgrid: `HashGridSDF` (slwarp.neural.hashgrid), a multiresolution hash encoding and
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
    # the depth range (finer failed on the small rig: notes/hashgrid.md): 2048 on the default rig, 512 on the small
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
    lambda_rc: float = option(1.0, "weight of the rendered-colour loss L_rc (0 only for the loss ablation)", min=0.0)
    lambda_sc: float = option(1.0, "weight of the surface-colour loss L_sc, from sc_start on", min=0.0)
    sc_start: int = option(1000, "iteration where L_sc starts", min=0)
    lambda_reg: float = option(0.1, "weight of the Eikonal loss L_reg", min=0.0)
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
    search_step_mm: float = option(1.0, "depth-search hypothesis spacing (mm)", above=0.0)
    search_stride: int = option(2, "depth search on every stride-th pixel", min=1)


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


# the extraction's stages (slwarp.neural.extraction.stages) in the order a preset lists them: an option that switches
# a stage on (STAGE_SWITCHES) puts it at its place in this order, after the stages that come before it here
STAGE_ORDER = ("marching_cubes", "depth", "depth_range", "flying_pixel", "confidence", "search_repair", "search_doubt",
               "refine", "uniform_fill", "repair_grow", "denoise")
# the stages of an extraction that names none: the mesh, its depth, the depth range, the flying-pixel filter and the
# confidence map with its filter
DEFAULT_STAGES = ("marching_cubes", "depth", "depth_range", "flying_pixel", "confidence")
# the options that switch a stage on (true, or a number above 0) and off (false, 0), by their flat names of old:
# `stages` and they always agree. search_repair and search_doubt share one place (the repair includes the doubt
# rule; while it runs, search_doubt says whether the doubt rule stays when the repair is switched off: _sync_stages)
STAGE_SWITCHES = {"edge_filter": "flying_pixel", "search_repair": "search_repair", "search_doubt": "search_doubt",
                  "refine_range": "refine", "uniform_fill": "uniform_fill", "repair_grow": "repair_grow",
                  "denoise_radius": "denoise"}
_SEARCH_STAGES = ("search_repair", "search_doubt")


class StageList(tuple):
    """The extraction's stage names in order (a tuple; written comma-separated, as the command line takes them)."""

    def __str__(self) -> str:
        return ",".join(self)


@dataclass
class ExtractionConfig:
    """From the trained field to a depth map.

    `stages` lists what runs, in order (slwarp.neural.extraction: each stage reads its own options below); the
    options of STAGE_SWITCHES add or remove their stage. Every extraction option acts after training: a resumed run
    may change it (e.g. extract again at another resolution)."""

    stages: tuple[str, ...] = option(StageList(DEFAULT_STAGES), "the extraction's stages in the order they run, "
                                     "comma-separated (slwarp.neural.extraction.STAGES); edge_filter, search_repair, "
                                     "search_doubt, refine_range, uniform_fill, repair_grow and denoise_radius add or "
                                     "remove theirs", resumable=True)
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
    # what the method knows about each pixel, as a map in [0, 1] written beside the depth (slwarp.neural.confidence);
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
                                       "least this many changed pixels of one surface (0: two agreeing neighbours "
                                       "suffice)", min=0, resumable=True)
    repair_grow: bool = option(False, "search repair: at the end, spread its changes to neighbouring pixels that kept "
                               "another surface's depth (over 20 mm off) where the codes fit the repaired surface "
                               "better; drops and fills nothing (needs search_repair)", resumable=True)
    search_doubt: bool = option(False, "drop depths that a per-pixel depth search (3x3 window) contradicts by more "
                                "than 6 mm and whose photometric confidence is below 0.7 (the background's depth on "
                                "a thin part); fills and replaces nothing (search_repair includes it)", resumable=True)
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
    refine_max_misfit: float = option(0.0, "refine only where the pattern model fits: skip the refinement when the "
                                      "median relative misfit of the lit pixels at the depth before refinement is above "
                                      "this (simulated scans 0.015-0.022, the real capture 0.026; 0: always refine)",
                                      min=0.0, resumable=True)
    denoise_radius: int = option(0, "last: each depth becomes the value at its pixel of a plane fitted (least squares "
                                 "in pixel coordinates) to the depths of its (2r + 1)^2 window that lie within "
                                 "denoise_footprints pixel footprints of its own (0: off)", min=0, resumable=True)
    denoise_footprints: float = option(4.0, "denoising: a window's depth takes part in the plane fit when within this "
                                       "many pixel footprints (z / f mm each) of the centre's depth", above=0.0,
                                       resumable=True)


SECTIONS = {"field": FieldConfig, "sampling": SamplingConfig, "schedule": ScheduleConfig, "init": InitConfig,
            "runtime": RuntimeConfig, "extraction": ExtractionConfig}


@dataclass(frozen=True)
class Option:
    """One option: its flat name, where it lives (section, key), its type and allowed values."""

    name: str
    section: str
    key: str
    type: object
    help: str
    min: float | None = None
    max: float | None = None
    above: float | None = None
    resumable: bool = False  # a resumed run may change it (see the module docstring)

    @property
    def choices(self) -> tuple | None:
        """The allowed words of a Literal option (with a number alternative: the words besides the number)."""
        words = [a for t in self._alternatives() if typing.get_origin(t) is Literal for a in typing.get_args(t)]
        return tuple(words) if words else None

    @property
    def is_bool(self) -> bool:
        return self.type is bool

    @property
    def is_list(self) -> bool:
        """A list of names (the extraction's stages): comma-separated on the command line, a list in YAML."""
        return typing.get_origin(self.type) is tuple

    def _alternatives(self) -> tuple:
        return typing.get_args(self.type) if typing.get_origin(self.type) in (typing.Union, _UnionType) else (self.type,)

    def _numeric(self):
        """int or float when the option takes a number (besides words or None), else None."""
        for t in self._alternatives():
            if t in (int, float):
                return t
        return None

    def allowed(self) -> str:
        """What the option takes, in words."""
        if self.is_list:
            return "a comma-separated list of names"
        parts = []
        num = self._numeric()
        if num is not None:
            rng = []
            if self.min is not None:
                rng.append(f">= {self.min:g}")
            if self.above is not None:
                rng.append(f"> {self.above:g}")
            if self.max is not None:
                rng.append(f"<= {self.max:g}")
            parts.append(("an integer" if num is int else "a number") + (" " + " and ".join(rng) if rng else ""))
        if self.choices:
            parts.append(("" if parts else "one of ") + ", ".join(map(str, self.choices)))
        if type(None) in self._alternatives():
            parts.append("none")
        if self.is_bool:
            parts.append("true or false")
        if self.type is str and self.key == "device":
            parts.append("auto, cpu, cuda or cuda:N")
        return " or ".join(parts)

    def metavar(self) -> str:
        """How --help shows the value: {a,b} for a choice of words, N (an integer) or X (a number) with the
        words it also takes, the key in capitals for text."""
        if self.is_list:
            return "NAME,..."
        if self.choices and self._numeric() is None:
            return "{" + ",".join(self.choices) + "}"
        word = {int: "N", float: "X"}.get(self._numeric(), self.key.upper())
        return "|".join([word, *(self.choices or ()), *(["none"] if type(None) in self._alternatives() else [])])

    def _fail(self, value):
        raise ConfigError(f"option {self.name} ({self.section}.{self.key}): {value!r} is not allowed; it takes {self.allowed()}")

    def check(self, value) -> None:
        """Raise ConfigError unless `value` is of the option's type and in its range."""
        if value is None:
            if type(None) not in self._alternatives():
                self._fail(value)
            return
        if self.is_list:
            if not (isinstance(value, (list, tuple)) and value and all(isinstance(v, str) and v.isidentifier()
                                                                      for v in value)):
                self._fail(value)
            return
        if self.choices and value in self.choices and not isinstance(value, bool):
            return
        if self.is_bool:
            if not isinstance(value, bool):
                self._fail(value)
            return
        num = self._numeric()
        if num is not None and isinstance(value, (int, float)) and not isinstance(value, bool):
            if (num is int and not isinstance(value, int)) or not math.isfinite(value):
                self._fail(value)
            if ((self.min is not None and value < self.min) or (self.max is not None and value > self.max)
                    or (self.above is not None and not value > self.above)):
                self._fail(value)
            return
        if self.type is str and isinstance(value, str) and (self.key != "device" or DEVICE_PATTERN.fullmatch(value)):
            return
        self._fail(value)

    def parse(self, text: str):
        """The value of `text` (a command-line word, a key=value spec, a YAML string), checked."""
        word = text.strip()
        if self.is_list:
            value = StageList(w.strip() for w in word.split(","))
            self.check(value)
            return value
        if self.is_bool:
            low = word.lower()
            if low not in ("true", "false", "1", "0", "yes", "no", "on", "off"):
                self._fail(text)
            value = low in ("true", "1", "yes", "on")
        elif self.choices and word in self.choices:
            value = word
        elif type(None) in self._alternatives() and word.lower() in ("none", "null"):
            value = None
        elif self._numeric() is not None:
            try:
                value = int(word) if self._numeric() is int else float(word)
            except ValueError:
                self._fail(text)
        else:
            value = word
        self.check(value)
        return value

    def coerce(self, value):
        """A value read from YAML: strings are parsed as on the command line (YAML reads 1e-4 as a string), an
        integer is accepted for a number; checked."""
        if isinstance(value, str):
            return self.parse(value)
        if self.is_list and isinstance(value, (list, tuple)):
            value = StageList(value)
        if isinstance(value, int) and not isinstance(value, bool) and self._numeric() is float:
            value = float(value)
        self.check(value)
        return value


_UnionType = type(int | None)


def _collect_options() -> dict[str, Option]:
    options: dict[str, Option] = {}
    for section, cls in SECTIONS.items():
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            md = f.metadata
            name = md.get("name") or f.name
            if name in options:
                raise RuntimeError(f"option name {name!r} ({section}.{f.name}) is not unique")
            options[name] = Option(name, section, f.name, hints[f.name], md["help"], md.get("min"), md.get("max"),
                                   md.get("above"), bool(md.get("resumable")))
    return options


@dataclass
class TrainConfig:
    """Everything that defines a run, in six sections (see the module docstring and PRESETS)."""

    field: FieldConfig = dataclasses.field(default_factory=FieldConfig)
    sampling: SamplingConfig = dataclasses.field(default_factory=SamplingConfig)
    schedule: ScheduleConfig = dataclasses.field(default_factory=ScheduleConfig)
    init: InitConfig = dataclasses.field(default_factory=InitConfig)
    runtime: RuntimeConfig = dataclasses.field(default_factory=RuntimeConfig)
    extraction: ExtractionConfig = dataclasses.field(default_factory=ExtractionConfig)

    def get(self, name: str):
        """The value of an option by its flat name."""
        opt = _option(name)
        return getattr(getattr(self, opt.section), opt.key)

    def with_options(self, **options) -> "TrainConfig":
        """A copy with options set by flat name (e.g. iters=300, init_iters=100, device="cpu"), validated."""
        sections = {name: dataclasses.replace(getattr(self, name)) for name in SECTIONS}
        for name, value in options.items():
            opt = _option(name)
            opt.check(value)
            setattr(sections[opt.section], opt.key, value)
        _sync_stages(sections["extraction"], options)
        return TrainConfig(**sections).validate()

    def validate(self) -> "TrainConfig":
        """Check every option's type and range and the rules between options; raise ConfigError naming the
        option, its value and what is allowed. Returns self."""
        for name, cls in SECTIONS.items():
            if not isinstance(getattr(self, name), cls):
                raise ConfigError(f"TrainConfig.{name} must be a {cls.__name__}, got {type(getattr(self, name)).__name__}")
        for opt in OPTIONS.values():
            opt.check(self.get(opt.name))
        s, f = self.sampling, self.field
        if s.up_sample_steps > 0 and s.n_importance % s.up_sample_steps:
            raise ConfigError(f"option n_importance: {s.n_importance} is not a multiple of up_sample_steps "
                              f"({s.up_sample_steps})")
        if f.skip is not None and not f.skip < f.layers:
            raise ConfigError(f"option skip: {f.skip} must be below layers ({f.layers}), or none")
        if f.grid_start_levels > f.grid_levels:
            raise ConfigError(f"option grid_start_levels: {f.grid_start_levels} must not exceed grid_levels "
                              f"({f.grid_levels})")
        if f.grid_finest != "auto" and f.grid_finest < f.grid_base:
            raise ConfigError(f"option grid_finest: {f.grid_finest} must not be below grid_base ({f.grid_base}), or auto")
        _check_stages(self.extraction)
        if self.extraction.edge_readmit and not self.extraction.edge_filter > 0:
            raise ConfigError("option edge_readmit: true needs edge_filter > 0 (it gives back what that filter dropped)")
        if self.extraction.repair_grow and not self.extraction.search_repair:
            raise ConfigError("option repair_grow: true needs search_repair: true (it spreads the repair's changes)")
        return self

    def fixed_options(self) -> dict:
        """{flat name: value} of every option a resumed run must keep: all but the `RESUMABLE` ones."""
        return {name: self.get(name) for name, opt in OPTIONS.items() if not opt.resumable}

    def to_dict(self) -> dict:
        """{section: {key: value}}: plain values, as YAML and checkpoints hold them (the stages as a list)."""
        doc = dataclasses.asdict(self)
        doc["extraction"]["stages"] = list(self.extraction.stages)
        return doc

    @classmethod
    def from_dict(cls, doc: dict, base: "TrainConfig | None" = None, source: str = "config") -> "TrainConfig":
        """`base` (default: TrainConfig()) with the values of doc {section: {key: value}} (all optional),
        validated. Unknown sections or keys raise ConfigError naming `source`."""
        if not isinstance(doc, dict):
            raise ConfigError(f"{source}: expected a mapping of sections ({', '.join(SECTIONS)}), got {type(doc).__name__}")
        sections = {name: dataclasses.replace(getattr(base or cls(), name)) for name in SECTIONS}
        for name, values in doc.items():
            if name not in SECTIONS:
                raise ConfigError(f"{source}: unknown section {name!r}; sections: {', '.join(SECTIONS)}")
            if not isinstance(values, dict):
                raise ConfigError(f"{source}: section {name} must be a mapping of options, got {values!r}")
            keys = {f.name: f for f in dataclasses.fields(SECTIONS[name])}
            for key, value in values.items():
                if (name, key) in REMOVED_OPTIONS:
                    if value:
                        warnings.warn(f"{source}: option {name}.{key} was removed ({REMOVED_OPTIONS[name, key]}); "
                                      f"its value {value!r} is ignored", stacklevel=2)
                    continue
                if key not in keys:
                    raise ConfigError(f"{source}: unknown option {name}.{key}; {name} has {', '.join(keys)}")
                opt = OPTIONS[keys[key].metadata.get("name") or key]
                try:
                    setattr(sections[name], key, opt.coerce(value))
                except ConfigError as e:
                    raise ConfigError(f"{source}: {e}") from None
        try:
            # a file of before `stages` (or one that sets a switch) has its switches add or remove their stages
            _sync_stages(sections["extraction"], doc.get("extraction") or {})
        except ConfigError as e:
            raise ConfigError(f"{source}: {e}") from None
        return cls(**sections).validate()


def _place(stages: list[str], name: str) -> None:
    """Insert stage `name` into `stages` after the last of them that STAGE_ORDER puts before it (stages it does not
    know are passed over)."""
    rank = STAGE_ORDER.index(name)
    at = max((i + 1 for i, s in enumerate(stages) if s in STAGE_ORDER and STAGE_ORDER.index(s) < rank), default=0)
    stages.insert(at, name)


def _sync_stages(ex: ExtractionConfig, given) -> None:
    """Make `stages` and the stage switches agree, in place: each switch in `given` (the options set just now) adds
    or removes its stage, then every switch reads from the list (a number switch keeps its value while its stage
    runs, 0 when it does not).

    search_repair and search_doubt share one place in the list: the repair (which includes the doubt rule), else the
    doubt rule alone, else neither. While the repair runs, search_doubt keeps its own value: whether the doubt rule
    stays when the repair is switched off (as the two options always behaved)."""
    stages = list(ex.stages)
    on = {opt: bool(getattr(ex, opt)) if opt in given else stage in stages for opt, stage in STAGE_SWITCHES.items()}
    if "search_doubt" not in given and "search_repair" in stages:
        on["search_doubt"] = bool(ex.search_doubt)
    if "search_doubt" not in given and "search_doubt" in stages:
        on["search_doubt"] = True
    if {"search_repair", "search_doubt"} & set(given):
        slot = "search_repair" if on["search_repair"] else "search_doubt" if on["search_doubt"] else None
        stages = [s for s in stages if s not in _SEARCH_STAGES or s == slot]
        if slot is not None and slot not in stages:
            _place(stages, slot)
    for opt in set(given) & STAGE_SWITCHES.keys() - {"search_repair", "search_doubt"}:
        stage = STAGE_SWITCHES[opt]
        if on[opt] and stage not in stages:
            _place(stages, stage)
        elif not on[opt] and stage in stages:
            stages.remove(stage)
    for opt, stage in STAGE_SWITCHES.items():
        value = getattr(ex, opt)
        if opt == "search_doubt":
            setattr(ex, opt, on[opt] if "search_repair" in stages else "search_doubt" in stages)
        elif isinstance(value, bool):
            setattr(ex, opt, stage in stages)
        elif stage not in stages:
            setattr(ex, opt, type(value)(0))
        elif not value > 0:
            raise ConfigError(f"option stages: {stage} runs with {opt} above 0, got {value}: give {opt} (or leave "
                              f"{stage} out)")
    ex.stages = StageList(stages)


def _check_stages(ex: ExtractionConfig) -> None:
    """ConfigError unless `stages` names each stage once, at most one of the search repair and its doubt rule, and
    agrees with the stage switches (which with_options, presets and config files keep in step with it)."""
    stages = list(ex.stages)
    twice = sorted({s for s in stages if stages.count(s) > 1})
    if twice:
        raise ConfigError(f"option stages: {', '.join(twice)} named more than once in {StageList(stages)}")
    if set(_SEARCH_STAGES) <= set(stages):
        raise ConfigError("option stages: names both search_repair and search_doubt; the repair includes the doubt "
                          "rule, so name one")
    for opt, stage in STAGE_SWITCHES.items():
        if opt == "search_doubt" and "search_repair" in stages:
            continue  # the repair's own setting: whether the doubt rule stays without it
        if bool(getattr(ex, opt)) != (stage in stages):
            raise ConfigError(f"option {opt}: {getattr(ex, opt)!r} disagrees with stages ({StageList(stages)}), "
                              f"which {'names' if stage in stages else 'does not name'} {stage}; set options through "
                              "with_options, a preset or a config file, which keep them in step")


OPTIONS: dict[str, Option] = _collect_options()
# options that configs saved by earlier versions may still hold: read past (with a warning when set), so that an
# old run's config.yaml or checkpoint still loads; {(section, key): why it went}
REMOVED_OPTIONS: dict[tuple[str, str], str] = {
    ("extraction", "search_confirm"): "it gave dropped pixels back at +0.003 to +0.05 mm of MAE on every GPU scan "
                                      "measured; edge_readmit does the same job better (notes/accuracy.md, sections "
                                      "10 and 16)",
}
# the options a resumed run may change (flat names); every other one is part of the run's identity
RESUMABLE: tuple[str, ...] = tuple(name for name, opt in OPTIONS.items() if opt.resumable)


def _option(name: str) -> Option:
    opt = OPTIONS.get(name)
    if opt is None:
        raise ConfigError(f"unknown option {name!r}; options: {', '.join(OPTIONS)}")
    return opt


# ----------------------------------------------------------------------------------------------
# presets

PRESETS: dict[str, TrainConfig] = {}
PRESET_SUMMARIES: dict[str, str] = {}


def _preset(name: str, summary: str, **options) -> None:
    PRESETS[name] = TrainConfig().with_options(**options)
    PRESET_SUMMARIES[name] = summary


# the paper: 4000 iterations, 2048 rays, 32 + 32 samples, NeuS MLP 8 x 256, Adam 1e-4 constant, lambda_sc 0 then 1
# after 1000 iterations, lambda_reg 0.1 (plus our depth-search start; TF32 on CUDA, which changed the bunny's MAE
# by 3% against full float32)
_preset("paper", "the paper's recipe, unchanged: 4000 iterations, 2048 rays, 32+32 samples, MLP 8x256, Adam 1e-4 (GPU)",
        matmul="tf32")
# measured better on the virtual scanner (default-rig bunny: MAE 0.77 mm against 2.0 mm for "paper"): NeuS's
# learning rate 5e-4 with cosine decay, and no surface-colour loss (it samples the sharp pattern at one point and
# disagrees with the blurred edges the camera sees)
# its extraction adds the photometric refinement (+-3 mm) and the search doubt rule. On the default rig (8 scenes,
# H200, bench/results/accuracy-cuda-doubt-default.md) the mean MAE is 0.186 mm against 0.298 with refinement alone,
# 0.386 with neither and 0.310 for GC(7); the doubt rule lowered the MAE on each of the 12 scenes measured on the
# default and vertical rigs (rods 1.352 -> 0.600 and 1.414 -> 0.764) for 0.1 to 0.5 points of completeness. On the
# other rigs (bench/results/accuracy-cuda-doubt-rigs.md) 0.196 (vertical), 0.147 (oblique), 0.229 mm (rolled)
# against GC(7)'s 0.271, 0.357, 0.405. The
# search repair with its changes kept only in groups of >= 100 pixels (repair_min_component): the same 32 trained
# fields (8 scenes x 4 rigs, bench/results/accuracy-cuda-component.md) give a mean MAE of 0.166 / 0.178 / 0.129 /
# 0.206 mm (default / vertical / oblique / rolled) against 0.187 / 0.210 / 0.147 / 0.221 with the doubt rule alone,
# and 0.6 to 1.5 points more completeness: the field never learns the 2.5 mm rods, the search finds them (rods
# 0.59 -> 0.41 mm on the default rig). Its doubt rule then also drops a contradicted depth whose switch the group
# rule refused (rods on the 4 rigs 0.41-0.55 -> 0.39-0.45 mm; bench/results/accuracy-cuda-doubt-fix-*.md). The
# repair without the group rule added 0.2 to 0.6 mm on every smooth scene (accuracy-cuda-oblique-rolled.md)
# the extraction of both defaults (tuned, cpu-hashgrid): refinement, then the search repair in groups (its doubt
# rule stays on by itself when a run turns the repair off)
# and the refinement only where the pattern model explains the images (REFINE_MAX_MISFIT)
# and the repair's growth (extraction.repair.grow_repair) into the pixels beside it that kept the background's depth
# by a chance fit: full-resolution rods, tuned's maps of 4 rigs grown offline (bench/results/grow-study.md) 0.183 / 0.285 / 0.183
# / 0.305 -> 0.178 / 0.236 / 0.168 / 0.275 mm (default / vertical / oblique / rolled), no pixel gained or lost; no
# change on the 4 checker maps (no repair there) nor, grown in the extraction, on vertical-rig steps
# (accuracy-cuda-grow-check.md, which also has vertical rods 0.264 -> 0.231 mm with the growth in the extraction);
# on the small rig with cpu-hashgrid nothing grows on any of the 8 scenes (accuracy-cpu-grow.md)
# the stages in order: the default ones, the search repair, the refinement, the uniform-code fill (measured with the
# surface term below), the repair's growth (after the refinement, so that the repaired depths it spreads are
# refined) and last the denoising (each preset gives its window: _GPU_DENOISE, cpu-hashgrid's); search_doubt keeps
# the doubt rule when a run switches the repair off
_DEFAULT_EXTRACTION = dict(stages=(*DEFAULT_STAGES, "search_repair", "refine", "uniform_fill", "repair_grow", "denoise"),
                           refine_range=3.0, refine_max_misfit=REFINE_MAX_MISFIT, repair_min_component=100,
                           search_doubt=True)
# the GPU presets' last stage, the edge-aware plane fit of 9x9 windows within 8 footprints (extraction.surface.denoise_depth):
# one H100, 8 scenes x default / vertical rig, the same trained fields extracted again
# (bench/results/accuracy-cuda-denoise.md): mean MAE tuned 0.134 / 0.137 -> 0.094 / 0.096 mm, accurate 0.152 / 0.153
# -> 0.098 / 0.099, fast 0.174 / 0.162 -> 0.124 / 0.113; better on each of the 48 scans (rods included: tuned 0.196 /
# 0.261 -> 0.151 / 0.216), completeness unchanged (it moves depths only). Radius 2 / 3 / 4 within 4 footprints:
# tuned 0.109 / 0.101 / 0.094 on the default rig; 8 footprints tied with 4 on tuned and was 0.002-0.003 mm better on
# the hash-grid presets. Larger windows not yet measured. The small rig's footprint is 4x the default rig's (a 9x9
# window would span 14 mm at 700 mm: 0.3 mm of bias on a 50 mm sphere), so cpu-hashgrid denoises 5x5 windows
_GPU_DENOISE = dict(denoise_radius=4, denoise_footprints=8.0)
# the surface term (surface_weight = surface_after = 1, its depths only in confirmed groups of >= 50 pixels) and the
# uniform-code fill: 32 scans (8 scenes x 4 rigs, 2 H200s, bench/results/accuracy-cuda-surface-group.md) give a mean
# MAE of 0.136 / 0.139 / 0.093 / 0.176 mm (default / vertical / oblique / rolled) against 0.166 / 0.178 / 0.129 /
# 0.206 without either (rods 0.41-0.55 -> 0.18-0.32 mm: the term holds the thin parts training loses), and 95.5 /
# 95.7 / 95.4 / 95.4% completeness (the term alone: 0.132 / 0.135 / 0.090 / 0.167 mm, 94.2 to 94.6%, per scan -1.7 to
# +1.2 points; the fill adds 1.0 to 1.3 points per scan for +0.002 to +0.011 mm)
# the edge readmission at photometric confidence >= 0.9 (one H100, the same fields re-extracted,
# bench/results/accuracy-cuda-edge-default.md, -edge-vertical.md): completeness -1.19 -> -0.94 points against GC(7)
# on the default rig, -0.90 -> -0.74 on the vertical one, for +0.003 mm on each (rods +0.013 / +0.014); at 0.8
# +0.005 mm, which took the vertical rig to 0.51x GC(7); asking 5 neighbours gave nothing back
_preset("tuned", "paper with lr 5e-4, cosine decay, no surface-colour loss, an SDF term at the depths the codes "
        "confirm, photometric depth refinement (+-3 mm, where the pattern model fits the images), the search repair "
        "(changes in groups of >= 100 pixels, grown into the neighbours that kept another surface), the uniform-code "
        "fill, the edge readmission and the edge-aware denoising: the most accurate measured on the virtual scanner (GPU "
        "default)",
        matmul="tf32", lr=5e-4, lr_decay="cosine", lambda_sc=0.0, surface_weight=1.0, surface_after=1.0,
        edge_readmit=True, **_DEFAULT_EXTRACTION, **_GPU_DENOISE)
# CPU: the tuned recipe with a smaller field and batch, minutes on two cores (small rig)
_preset("cpu", "tuned with a 4x64 field, 384 rays, 1500 iterations: minutes on two CPU cores (small rig)",
        iters=1500, rays=384, n_samples=24, n_importance=16, up_sample_steps=2, lr=5e-4, lr_decay="cosine",
        lambda_sc=0.0, hidden=64, layers=4, skip=2, n_freqs=6, search_step_mm=2.0, mc_resolution=192,
        checkpoint_every=250, log_every=25)
# tests: a few hundred iterations of a smaller field
_preset("tiny", "a 3x48 field for 300 iterations: tests", iters=300, rays=256, n_samples=16, n_importance=8,
        up_sample_steps=1, lr=5e-4, lr_decay="cosine", sc_start=100, hidden=48, layers=3, skip=None, n_freqs=4,
        init_iters=100, search_step_mm=2.0, search_stride=3, mc_resolution=128, checkpoint_every=100, log_every=25)


# the hash-grid field (slwarp.neural.hashgrid; notes/hashgrid.md): Adam 1e-3 for its MLP and the variance, 1e-2
# for the tables, cosine decay, no surface-colour loss, levels coarse to fine. Their iterations and level schedules
# are first choices for the GPU: the lead's GPU accuracy sweep (bench/train_variants.py) settles them.
_HASHGRID = dict(field="hashgrid", lr=1e-3, lr_decay="cosine", lambda_sc=0.0, grid_table_lr_factor=10.0)
# a GPU depth map as soon as possible: 1000 iterations with all 8 levels on by iteration 200 + 300; 8 levels and
# the 4-tap gradient as accurate: on default-rig bunny, steps and torus (H100, bench/results/fast-variants-cuda.md)
# scan to depth map 9.5 -> 7.1 s for a mean MAE of 0.665 against 0.662 mm with 16 levels and 5 evaluations.
# With tuned's surface term and extraction and 1024 rays (default and vertical rigs, 8 scenes each, one H100,
# bench/results/accuracy-cuda-hashgrid-schedule.md): mean MAE 0.200 / 0.165 mm; default-rig bunny
# 0.325 -> 0.119 mm for 7.1 s from a loaded scan instead of 5.6 (bench/results/train-speed-cuda-fast-x.md). 2048
# rays gave 0.202 / 0.163 mm in 8.4 s, 600 iterations of 1024 rays 0.280 / 0.268 mm in 6.2 s
# The free-space term (free_space; one H100, 8 scenes x default / vertical rig,
# bench/results/accuracy-cuda-free-space.md, -free-space-2.md): mean MAE 0.196 / 0.170 -> 0.176 / 0.162 mm at 0.2
# (boxes 0.240 -> 0.160, steps 0.368 -> 0.293 on the default rig), 0.184 / 0.160 at 0.1, 0.197 / 0.161 at 0.5 and
# 0.260 / 0.161 at 1 (default-rig steps lost 8 points of completeness: 1000 steps of the fast tables overshoot)
# Two up-sampling steps instead of four (the same 32 + 32 samples; one H100, 8 scenes x default / vertical rig,
# bench/results/fast-upsample-steps.md): mean MAE 0.130 / 0.114 mm against 0.126 / 0.113 with four (0.137 / 0.117 with
# one); steady state 1.79 -> 1.61 ms per step, 4.4 -> 4.0 s from a loaded scan (default-rig bunny, python
# bench/train_speed.py --preset fast --end-to-end: bench/results/train-speed-cuda-fast-e2e-16b.md, -16c.md). Fewer iterations or samples
# cost far more (bench/results/fast-speed-variants.md: 600 + 120 iterations 0.234 / 0.196 mm)
# NeuS's variance at 2x the learning rate and the free-space term at 0.5 (one H100, 8 scenes x default / vertical rig,
# three sweeps: simulator seeds 0 and 1, bench/results/accuracy-cuda-fast-tuning-s0.md, -s1.md, and -fast-free-space-c.md):
# mean MAE 0.133 / 0.115, 0.126 / 0.111 mm -> 0.126 / 0.106, 0.122 / 0.105 (0.120 / 0.107 in the third); steps
# 0.312 -> 0.253 and 0.241 -> 0.220 on the default rig, spheres 0.099 -> 0.136 and 0.096 -> 0.107. The variance
# alone at 2x: 0.129 / 0.106 and 0.127 / 0.106; at 4x 0.119 and 0.141 on the default rig (accuracy-cuda-variance-lr.md,
# -fast-variance-lr-2.md); levels every 30 iterations or the tables at 20x lr: no better
# The surface term also where the field lies in front of the map (surface_in_front; one H100, 8 scenes x default /
# vertical rig, seeds 0 and 1, bench/results/accuracy-cuda-fast-surface-in-front-s0.md, -s1.md): mean MAE 0.123 /
# 0.107, 0.118 / 0.107 mm -> 0.104 / 0.105, 0.105 / 0.107 (tuned: 0.094 / 0.096); default-rig steps 0.226 -> 0.109
# and spheres 0.141 -> 0.097 in the first (the field had carried the upper step over the lower one), rods 0.178 ->
# 0.188. Oblique / rolled rigs (-oblique-rolled.md) 0.083 / 0.149 -> 0.082 / 0.138. accurate did not gain
# (accuracy-cuda-accurate-surface-in-front-s0.md: 0.093 / 0.096 -> 0.096 / 0.097), so it keeps the option off.
# Then 800 iterations instead of 1000 (the same rigs and seeds, bench/results/accuracy-cuda-fast-iters-s0.md, -s1.md,
# -oblique-rolled.md): mean MAE 0.104 / 0.105, 0.106 / 0.107 mm -> 0.107 / 0.107, 0.107 / 0.107 (900: 0.106 / 0.107),
# oblique / rolled 0.081 / 0.140 -> 0.084 / 0.142, for 2.65 -> 2.31 s from a loaded scan to the depth map (default-rig
# bunny, bench/results/train-speed-cuda-fast-e2e-20c.md, -fast-800-e2e-20.md): the 3 s target with room for a
# slower host (the same preset took 2.82-3.01 s on a machine just after a sweep). Levels every 40: no better
_preset("fast", "hash-grid field (8 levels, 4-tap gradient), 200 + 800 iterations of 1024 rays, levels switched on "
        "quickly, two up-sampling steps, NeuS's variance at 2x the rate, with tuned's surface term (on both sides of "
        "the map) and extraction and a free-space term: a depth map as soon as possible (GPU)",
        matmul="tf32", iters=800, init_iters=200, rays=1024, up_sample_steps=2, grid_levels=8,
        grid_gradient="finite_difference_4",
        grid_start_levels=2, grid_level_every=50, mc_resolution=256, checkpoint_every=1000, surface_weight=1.0,
        surface_after=1.0, surface_in_front=True, free_space=0.5, variance_lr_factor=2.0, **_DEFAULT_EXTRACTION,
        **_GPU_DENOISE, **_HASHGRID)
# the accurate hash-grid recipe: 8 levels (growth 2), the 4-tap gradient, and tuned's surface term and extraction.
# Default and vertical rigs, 8 scenes each, H200 (bench/results/accuracy-cuda-hashgrid.md): 8 levels gave a mean
# MAE of 0.378 / 0.282 mm against 0.351 / 0.268 with 16 and 0.369 / 0.295 with 12; the 4-tap gradient (f from the
# taps' mean) then 0.330 / 0.266, better on all 16 scans, with one field evaluation in five fewer. With tuned's
# surface term and extraction (one H100, bench/results/accuracy-cuda-accurate-full.md) 0.196 / 0.162 mm (steps
# 0.792 -> 0.445, rods 0.885 -> 0.180 on the default rig; the other scans 0.000 to 0.006 mm worse) and 95.6 / 95.9% completeness; without the surface term
# (accuracy-cuda-accurate-noterm.md, default rig) 0.220 (rods 0.376). The term costs training time: 15.1 s against
# 13.7 for 4300 iterations on an H100 (bench/results/train-speed-cuda-accurate-full.md, -accurate.md); with the faster
# extraction 15.0 s of training and 19.6 s from a loaded scan to the depth map (train-speed-cuda-accurate-e2e.md)
# Fewer iterations measured better (the same 16 scans, bench/results/accuracy-cuda-hashgrid-schedule.md): 2000
# iterations with a level every 100 give 0.186 / 0.153 mm against 0.196 / 0.162 for 4000 (better on 14 of the 16
# scans; rods 0.180 -> 0.199 and 0.211 -> 0.222), 1500 with a level every 75 0.192 / 0.157; the long schedule's
# finest tables fit the images' noise (its error within 5 mm was 0.154 mm against fast's 0.142). Training 15.0 ->
# 7.8 s, scan to depth map 19.6 -> 12.9 s (bench/results/train-speed-cuda-accurate-2000.md). A smaller finest level
# (1024 cells: 0.198 / 0.169), two hidden layers (0.195 / 0.164) and a table learning rate of 3x lr (0.201 / 0.162)
# at 4000 iterations did not help
# The free-space term (free_space = 1; one H100, the same 16 scans, bench/results/accuracy-cuda-free-space.md and
# -free-space-2.md): mean MAE 0.188 / 0.153 -> 0.151 / 0.153 and 0.152 / 0.153 mm in two runs (0.151 / 0.153 at
# 0.5): default-rig steps 0.439 -> 0.141 (the field had bridged the gaps between the steps: 847 pixels of the wall
# 250 mm in front), bunny 0.131 -> 0.120; no scan more than 0.005 mm worse
# NeuS's variance at 4x the learning rate (variance_lr_factor; one H100, bench/results/accuracy-cuda-variance-lr.md
# and -variance-lr-c.md against accuracy-cuda-speed.md): default / vertical-rig mean MAE 0.098 / 0.100 -> 0.093 /
# 0.0975 mm (tuned: 0.094 / 0.096), better or equal on 15 of the 16 scans (default-rig rods 0.142 -> 0.116; vertical
# torus 0.086 -> 0.087). At 1x inv_s was still rising at the end: Adam moves the variance's v by about lr per step
_preset("accurate", "hash-grid field (8 levels, 4-tap gradient), 2000 iterations of the paper's batch, levels "
        "coarse to fine, NeuS's variance at 4x the rate, with tuned's surface term and extraction and a free-space "
        "term: several times faster than tuned, as accurate on the default rig (GPU)",
        matmul="tf32", iters=2000, grid_levels=8, grid_gradient="finite_difference_4", grid_start_levels=2,
        grid_level_every=100, variance_lr_factor=4.0, surface_weight=1.0, surface_after=1.0, free_space=1.0,
        **_DEFAULT_EXTRACTION, **_GPU_DENOISE, **_HASHGRID)
# CPU: the cpu preset's step on a small hash grid (8 levels of 2^15 entries; finer tables are cache-bound on
# one thread): small rig, bunny/vase/boxes mean MAE 0.575 mm against 0.749 for cpu at about its time per step
# its extraction: the refinement and, as tuned, the search repair in groups of >= 100 pixels: small rig, 8 scenes,
# the same fields (bench/results/accuracy-cpu-component*.md): rods 1.088 -> 0.886 mm, steps 0.527 -> 0.501, boxes and
# checker -0.003 / -0.001, the other four unchanged, about 2 s more extraction (the repair without the group rule
# measured worse on the CPU demo: 0.268 mm against 0.260 without it)
# the 4-tap gradient as accurate: small rig, bunny/vase/boxes mean MAE 0.345 -> 0.328 mm, training 201 -> 164 s
# (bench/results/cpu-hashgrid-gradient-cpu.md). The uniform-code fill: small rig, 8 scenes, the same fields
# (bench/results/accuracy-cpu-uniform-fill.md): completeness 93.33 -> 94.31%, MAE 0.410 -> 0.414 mm (checker
# 0.365 -> 0.392, the others within +0.003 or better); not yet measured on a GPU, so tuned keeps it off
# the edge-aware denoising of 5x5 windows within 4 footprints (small rig, 8 scenes, the same fields extracted again;
# python bench/accuracy_sweep.py --small --presets cpu-hashgrid --rigs default --also-extract denoise_radius=1,...
# --workers 2, bench/results/accuracy-cpu-denoise.md): mean MAE 0.421 -> 0.361 mm (3x3: 0.385; 8 footprints 0.362),
# better on all 8 scenes (bunny 0.243 -> 0.196, rods 0.896 -> 0.834); small vertical rig 0.356 -> 0.295 mm, all 8 better
# (accuracy-cpu-denoise-vertical.md)
_preset("cpu-hashgrid", "cpu with the hash-grid field (8 levels, 2^15 entries, 4-tap gradient), photometric depth "
        "refinement (+-3 mm, where the pattern model fits the images), the search repair in groups (grown), the "
        "uniform-code fill and the edge-aware denoising (5x5 windows): better MAE in less time than cpu (small rig)",
        grid_gradient="finite_difference_4", iters=1500, rays=384, n_samples=24, n_importance=16, up_sample_steps=2,
        search_step_mm=2.0, mc_resolution=192, checkpoint_every=250, log_every=25, grid_levels=8, grid_log2_table=15,
        denoise_radius=2, denoise_footprints=4.0, **_DEFAULT_EXTRACTION, **_HASHGRID)

# the preset a run gets when it names none, per device type. CPU: cpu-hashgrid, measured on the small rig with the
# trainer (bunny MAE 0.479 mm against 0.606 for cpu; mean of bunny, vase, boxes 0.575 against 0.749 mm at 0.95x cpu's
# time per step). GPU: tuned (see its comment). Real capture: the refinement made the chessboard plate 2.4x less
# flat (bench/results/chessboard-cuda.md); both defaults skip it there by themselves, as the pattern model misfits
# the real images (refine_max_misfit; notes/accuracy.md, section 14).
DEFAULT_PRESET = {"cuda": "tuned", "cpu": "cpu-hashgrid"}


def preset(name: str, **options) -> TrainConfig:
    """A copy of preset `name` with options set by flat name (see OPTIONS), validated."""
    if name not in PRESETS:
        raise ConfigError(f"unknown preset {name!r}; presets: {', '.join(PRESETS)}")
    return PRESETS[name].with_options(**options)


def parse_assignments(items) -> dict:
    """['iters=300', 'field=hashgrid'] -> {flat option name: value}, each value parsed and checked as on the
    command line; ConfigError naming the item when it is not KEY=VALUE with KEY an option (see OPTIONS)."""
    options = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or key not in OPTIONS:
            raise ConfigError(f"{item!r}: expected KEY=VALUE with KEY an option of slwarp.neural.config")
        options[key] = OPTIONS[key].parse(value)
    return options


def default_preset_name(device) -> str:
    """The default preset of a device (a torch.device or its type as a string): DEFAULT_PRESET's entry for
    CUDA, the CPU's for any other device."""
    return DEFAULT_PRESET["cuda" if getattr(device, "type", device) == "cuda" else "cpu"]


# ----------------------------------------------------------------------------------------------
# YAML


def load_config(path, base: TrainConfig | None = None) -> TrainConfig:
    """A config from a YAML file of sections (field, sampling, ...: mappings of options; any may be left out and
    keeps `base`'s values, default TrainConfig()). A `fitted` section (values a run fitted, written by
    `save_config`) is read past, so a run's config.yaml can be passed back."""
    import yaml

    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file not found: {path}")
    try:
        doc = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise ConfigError(f"{path}: not valid YAML ({e})") from None
    if isinstance(doc, dict):
        doc = {k: v for k, v in doc.items() if k != "fitted"}
    return TrainConfig.from_dict(doc if doc is not None else {}, base, source=str(path))


def save_config(path, config: TrainConfig, fitted: dict | None = None) -> None:
    """Write the config as YAML (every section and option) and, when given, the values the run fitted in a
    `fitted` section."""
    import yaml

    doc = config.to_dict()
    if fitted is not None:
        doc["fitted"] = _plain(fitted)
    Path(path).write_text(yaml.safe_dump(doc, sort_keys=False, default_flow_style=False, width=120))


def _plain(x):
    """Nested dicts/lists with numpy scalars turned into Python numbers (YAML's safe dumper needs them)."""
    if isinstance(x, dict):
        return {_plain(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if hasattr(x, "item") and callable(x.item):
        return x.item()
    return x
