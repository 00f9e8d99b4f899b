"""What the extraction's stages share: the pattern model's inputs, bundled once (`ModelInputs`), the trained field
(`TrainedField`), the state a stage takes and returns (`State`), the pixel fates and the result (`Extraction`)."""
from __future__ import annotations

import contextlib
import dataclasses
import functools
import threading
from typing import NamedTuple

import numpy as np
import torch

from ..pattern_model import lit_with_contrast, offset_and_modulation
from ..start import window_step_of
from ..training import pattern_model_inputs


def _host(x) -> np.ndarray:
    """A tensor or array as a numpy array on the host (the same object when it is one already)."""
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


@dataclasses.dataclass(frozen=True, eq=False)
class ModelInputs:
    """The pattern model's inputs at extraction, bundled once: camera and projector; images [N, H, W] and patterns
    [N, Hp, Wp] as rendered (blurred) as the model holds them (on a GPU the renderer's tensors, so that the model
    runs there; else numpy); depth_range (near, far) mm; valid [H, W] bool: the pixels the depth map may cover (lit
    with contrast, and the scan's mask when asked; None: every pixel); lit [H, W] bool: the pixels lit with contrast
    (default: from the images' modulation at CONTRAST_THRESHOLD); region [H, W] bool: where the uniform-code fill may
    add pixels (None: anywhere); raw_patterns [N, Hp, Wp]: the patterns unblurred (the refinement fits its own
    blur); device: where the searches and the refinement run; step_mm: the depth searches' hypothesis spacing;
    host_images [N, H, W]: the images as numpy (default: `images` brought to the host); lens_halo: the share of the
    lens halo in the patterns (the trainer's, fitted or given; 0: none); window_step: camera px between the pixels of
    the depth searches' windows (the start's: a set designed for spaced windows is searched with its step)."""

    camera: object
    projector: object
    images: object
    patterns: object
    depth_range: tuple[float, float]
    valid: np.ndarray | None = None
    lit: np.ndarray | None = None
    region: np.ndarray | None = None
    raw_patterns: np.ndarray | None = None
    device: object = "cpu"
    step_mm: float = 1.0
    host_images: np.ndarray | None = None
    lens_halo: float = 0.0
    window_step: int = 1

    def __post_init__(self):
        # frozen: the derived defaults are set once, here
        if self.host_images is None:
            object.__setattr__(self, "host_images", _host(self.images))
        if self.lit is None:
            object.__setattr__(self, "lit", lit_with_contrast(offset_and_modulation(self.host_images)[1]))

    @functools.cached_property
    def host_patterns(self) -> np.ndarray:
        """The patterns as rendered, as numpy (copied from the device once, when first asked)."""
        return _host(self.patterns)

    @property
    def model(self) -> tuple:
        """(camera, projector, images, patterns): the arguments the pattern model's functions begin with."""
        return self.camera, self.projector, self.images, self.patterns

    @classmethod
    def from_trainer(cls, trainer, valid: np.ndarray | None = None, region: np.ndarray | None = None) -> "ModelInputs":
        """The bundle of a trainer's frames (`training.pattern_model_inputs`), rig, depth range, lit map and device;
        valid and region as the caller restricts them."""
        images, patterns = pattern_model_inputs(trainer)
        n = trainer.n_frames
        return cls(trainer.scan.camera, trainer.scan.projector, images, patterns, trainer.depth_range, valid=valid,
                   lit=trainer.renderer.valid_map.cpu().numpy(), region=region, raw_patterns=trainer.scan.patterns[:n],
                   device=trainer.device, step_mm=trainer.cfg.init.search_step_mm,
                   host_images=trainer.scan.images[:n], lens_halo=float(getattr(trainer, "halo_share", 0.0)),
                   window_step=window_step_of(trainer.scan, trainer.cfg, n))


# what became of each camera pixel at extraction (the values of Extraction.fate): with a depth, "measured" (the
# field's, refined), "repaired" (a depth search's, extraction.repair, or the depth across an edge its codes fit,
# extraction.edges) or "filled" (the uniform-code fill); without, the stage that left it without one: "no_contrast"
# (outside the lit-with-contrast map the decoders also use: shadows, dark albedo, codes that never change),
# "no_surface" (no mesh hit), then the filters in their order ("edge_side", registered by its stage, after them)
PIXEL_FATES = ("measured", "repaired", "filled", "no_contrast", "no_surface", "out_of_range", "flying_pixel",
               "low_confidence", "search_doubt")
FATE = {name: i for i, name in enumerate(PIXEL_FATES)}
# PIXEL_FATES and, after them, the fates that stages defined elsewhere declare (`register_fate`)
_FATES = list(PIXEL_FATES)


_FATES_LOCK = threading.Lock()  # extractions of a batch may run in two threads at once


def register_fate(name: str) -> int:
    """The index of fate `name` in the fate maps, a new one appended after PIXEL_FATES the first time."""
    with _FATES_LOCK:
        if name not in _FATES:
            if len(_FATES) == 256:
                raise ValueError(f"fate {name!r}: a fate map (uint8) holds 256 fates, all taken")
            _FATES.append(name)
        return _FATES.index(name)


def forget_fate(name: str) -> None:
    """Drop a fate that register_fate appended (PIXEL_FATES stay); the ones after it move down by one."""
    if name in PIXEL_FATES:
        raise ValueError(f"fate {name!r} is one of PIXEL_FATES")
    with _FATES_LOCK:
        if name in _FATES:
            _FATES.remove(name)


def pixel_fates() -> tuple[str, ...]:
    """The names of the fate maps' values: PIXEL_FATES, then the registered ones."""
    return tuple(_FATES)


def fate_counts(fate: np.ndarray, names: tuple[str, ...] | None = None) -> dict:
    """{fate name: pixels} of a fate map [H, W] (indices into `names`, default `pixel_fates()`), every fate named."""
    names = pixel_fates() if names is None else names
    counts = np.bincount(np.asarray(fate).ravel(), minlength=len(names))
    return {name: int(c) for name, c in zip(names, counts)}


class TrainedField(NamedTuple):
    """The trained field as the extraction uses it: sdf (the network, x [..., 3] mm -> SDF mm), its working volume,
    the renderer around it (the peak and agreement confidences render through it) and rays, the rays per render
    chunk (the training batch, so that a compiled field sees no new shape)."""

    sdf: torch.nn.Module
    volume: object
    renderer: object
    rays: int

    @classmethod
    def from_trainer(cls, trainer) -> "TrainedField":
        return cls(trainer.field, trainer.volume, trainer.renderer, trainer.cfg.sampling.rays)


@dataclasses.dataclass(frozen=True, eq=False)
class State:
    """What a stage takes and returns (`stage(state) -> state`; a stage returns new arrays and never writes into the
    state's). depth [H, W] mm, NaN where none (None before a depth stage); confidence [H, W] in [0, 1], NaN where no
    depth (None before the confidence stage); fate [H, W] uint8 (indices into `pixel_fates()`) and timings (seconds
    per stage and counts): the runner's, which only it writes; changed [H, W] bool: the pixels whose depth the last
    stage set, moved or removed (the runner's); mesh: the marching-cubes mesh (trimesh, mm) or None; field_depth
    [H, W] mm: the field's depth before any mask or filter (the uniform-code fill reads it); info: the counts the
    last stage reports, which the runner moves into timings; progress: show a bar for long stages."""

    inputs: ModelInputs
    field: TrainedField
    fate: np.ndarray
    timings: dict
    depth: np.ndarray | None = None
    confidence: np.ndarray | None = None
    changed: np.ndarray | None = None
    mesh: object = None
    field_depth: np.ndarray | None = None
    info: dict = dataclasses.field(default_factory=dict)
    progress: bool = False

    def replace(self, **changes) -> "State":
        """A copy with the named fields replaced."""
        return dataclasses.replace(self, **changes)

    @classmethod
    def start(cls, inputs: ModelInputs, field: TrainedField, progress: bool = False) -> "State":
        """The state before the first stage: no depth yet; fate "measured" inside inputs.valid, "no_contrast"
        outside."""
        H, W = inputs.camera.height, inputs.camera.width
        fate = np.full((H, W), FATE["measured"], np.uint8)
        if inputs.valid is not None:
            fate[~np.asarray(inputs.valid, bool)] = FATE["no_contrast"]
        return cls(inputs, field, fate, {"dropped": {}}, progress=progress)


class Extraction(NamedTuple):
    """extract_depth's result: depth [H, W] mm and confidence [H, W] in [0, 1] (NaN where no depth), the mesh
    (trimesh, mm), timings (seconds per stage and counts, JSON-safe) and fate [H, W] uint8 (the index in
    `pixel_fates()` of what became of each pixel)."""

    depth: np.ndarray
    confidence: np.ndarray
    mesh: object
    timings: dict
    fate: np.ndarray


@contextlib.contextmanager
def evaluating(module: torch.nn.Module):
    """The module in eval mode inside the block, in the mode it had after it."""
    was_training = module.training
    module.eval()
    try:
        yield module
    finally:
        module.train(was_training)
