"""The extraction's stages: each a small object holding its own settings (extraction options, by their flat names)
with one call, `stage(state) -> state` (state.State).

A stage is a dataclass subclass of `Stage` with a `name`; defining it registers it in STAGES, and naming it in a
config's `stages` (a preset's list, `--stages`, a config file) runs it there. Its fields are the extraction options
it reads (config.ExtractionConfig: their types, ranges and help live there; `Stage.from_config` fills them). It
returns a new state with what it changed: depth, mesh, confidence (when `scores`) and `info`, the counts it reports.
The runner (extraction.runner) does the rest the same way for every stage: it times it, gives the pixels it left
without depth the fate `drops`, those it gave a depth of its own the fate `marks` (a moved depth keeps its fate),
counts its drops and scores the confidence of the depths it changed. A stage with nothing to do returns its input.

Order between stages is structure: `after` names the stages that must run before it (checked when the list is
built, runner.build_stages).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ..pattern_model import photometric_confidence, refine_where_model_fits, refinement_generalises
from .confidence import depth_confidence
from .edges import settle_edge_sides
from .fill import fill_uniform_codes
from .repair import doubt_by_search, grow_repair, repair_by_search, scaled_min_component
from .state import FATE, State, evaluating, register_fate
from .steps import split_ramps
from .surface import (denoise_depth, extract_mesh, edge_band_masks, fill_pinholes, flying_pixel_filter, mesh_depth,
                      readmit_edge_pixels, sphere_trace_depth)

# the stages by name: every subclass of Stage with a name, as it is defined
STAGES: dict[str, type["Stage"]] = {}


class Stage:
    """The base of an extraction stage (see the module docstring). Class attributes: name (what a config's `stages`
    calls it), drops / marks (the fate of the pixels it leaves without depth / gives a depth of its own; None: it
    does not), scores (it sets the confidence of the depths it changes itself; else the runner scores them), after
    (the stages that must run before it)."""

    name: ClassVar[str]
    drops: ClassVar[str | None] = None
    marks: ClassVar[str | None] = None
    scores: ClassVar[bool] = False
    after: ClassVar[tuple[str, ...]] = ("depth",)

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        name = cls.__dict__.get("name")
        if name is None:
            return
        if name in STAGES:
            raise TypeError(f"extraction stage {name!r}: the name is taken by {STAGES[name].__qualname__}")
        STAGES[name] = cls
        for fate in (cls.__dict__.get("drops"), cls.__dict__.get("marks")):
            if isinstance(fate, str):
                register_fate(fate)

    @classmethod
    def from_config(cls, extraction) -> "Stage":
        """The stage with its settings (its dataclass fields; a stage that is no dataclass has none) read from an
        ExtractionConfig by their names."""
        fields = dataclasses.fields(cls) if dataclasses.is_dataclass(cls) else ()
        return cls(**{f.name: getattr(extraction, f.name) for f in fields})

    def __call__(self, state: State) -> State:
        raise NotImplementedError(f"extraction stage {self.name} ({type(self).__qualname__}) defines no __call__")


def unregister_stage(name: str) -> None:
    """Remove stage `name` from STAGES (a stage defined for a while, as tests do)."""
    STAGES.pop(name, None)


@dataclass(frozen=True)
class MarchingCubes(Stage):
    """The field's zero level as a mesh (surface.extract_mesh: Warp's marching cubes on a GPU, scikit-image's on the
    CPU), the volume before the near plane left empty."""

    name = "marching_cubes"
    after = ()
    mc_resolution: int

    def __call__(self, state: State) -> State:
        f, i = state.field, state.inputs
        with evaluating(f.sdf):
            mesh = extract_mesh(f.sdf, f.volume, self.mc_resolution, i.device, progress=state.progress,
                                depth_range=i.depth_range)
        return state.replace(mesh=mesh)


@dataclass(frozen=True)
class FieldDepth(Stage):
    """The depth map [H, W] mm: the mesh ray-cast (depth_method 'mesh', surface.mesh_depth) or the field
    sphere-traced ('sphere', surface.sphere_trace_depth), kept inside inputs.valid; the unmasked map is kept as
    state.field_depth."""

    name = "depth"
    drops = "no_surface"
    depth_method: str

    @property
    def after(self) -> tuple[str, ...]:
        return ("marching_cubes",) if self.depth_method == "mesh" else ()

    def __call__(self, state: State) -> State:
        i = state.inputs
        if self.depth_method == "sphere":
            with evaluating(state.field.sdf):
                raw = sphere_trace_depth(state.field.sdf, i.camera, i.depth_range, i.device, valid=i.valid)
        else:
            raw = mesh_depth(state.mesh, i.camera, i.device)
        depth = raw if i.valid is None else np.where(i.valid, raw, np.nan).astype(np.float32)
        return state.replace(depth=depth, field_depth=raw)


@dataclass(frozen=True)
class DepthRange(Stage):
    """Depths outside the depth range (near, far) dropped."""

    name = "depth_range"
    drops = "out_of_range"

    def __call__(self, state: State) -> State:
        near, far = state.inputs.depth_range
        depth = state.depth.copy()
        depth[(depth < near) | (depth > far)] = np.nan
        return state.replace(depth=depth)


@dataclass(frozen=True)
class FlyingPixelFilter(Stage):
    """The pixels on depth edges dropped (surface.flying_pixel_filter: a jump above edge_filter pixel footprints to
    a neighbour); with edge_readmit, those on one side of their edge whose codes confirm them given back
    (surface.readmit_edge_pixels; info edge_readmitted)."""

    name = "flying_pixel"
    drops = "flying_pixel"
    edge_filter: float
    edge_readmit: bool
    edge_readmit_support: int
    edge_readmit_confidence: float

    def __call__(self, state: State) -> State:
        i = state.inputs
        depth = flying_pixel_filter(state.depth, i.camera, self.edge_filter, device=i.device)
        readmitted = 0
        if self.edge_readmit:
            back = readmit_edge_pixels(state.depth, depth, i.camera, self.edge_filter,
                                       lambda d: photometric_confidence(d, *i.model),
                                       min_support=self.edge_readmit_support,
                                       min_confidence=self.edge_readmit_confidence, device=i.device)
            depth = np.where(back, state.depth, depth).astype(np.float32)
            readmitted = int(back.sum())
        return state.replace(depth=depth, info={"edge_readmitted": readmitted})


@dataclass(frozen=True)
class ConfidenceFilter(Stage):
    """The confidence map of the depth (extraction.confidence, the term `confidence`), and the pixels below
    min_confidence dropped (0: none)."""

    name = "confidence"
    scores = True
    confidence: str
    min_confidence: float

    @property
    def drops(self) -> str | None:
        return "low_confidence" if self.min_confidence > 0 else None

    def __call__(self, state: State) -> State:
        confidence = depth_confidence(state.inputs, state.depth, self.confidence, state.field)
        depth = state.depth
        if self.min_confidence > 0:
            drop = ~(confidence >= self.min_confidence)
            depth = depth.copy()
            depth[drop] = np.nan
            confidence[drop] = np.nan
        return state.replace(depth=depth, confidence=confidence)


@dataclass(frozen=True)
class SearchRepair(Stage):
    """Where a per-pixel depth search contradicts the field or fills its holes (thin parts it missed), its depth,
    kept in connected groups of repair_min_component pixels (counted as on a 1280 x 1024 camera:
    repair.scaled_min_component); contradicted depths the codes do not support dropped (repair.repair_by_search;
    info repair). Needs inputs.valid (none: nothing to search)."""

    name = "search_repair"
    drops = "search_doubt"
    marks = "repaired"
    min_confidence: float
    repair_min_component: int
    doubt_confidence: float

    def __call__(self, state: State) -> State:
        if state.inputs.valid is None:
            return state
        # no flying-pixel filter on the changed pixels: a search has no smoothness to bend it across a depth edge,
        # and a thin part is all edge
        min_component = scaled_min_component(self.repair_min_component, state.depth.shape)
        depth, info = repair_by_search(state.depth, state.inputs, self.min_confidence, min_component=min_component,
                                       doubt_confidence=self.doubt_confidence)
        info["kept"] = int((np.isfinite(depth) & ~(depth == state.depth)).sum())
        info["min_component"] = min_component
        return state.replace(depth=depth, info={"repair": info})


@dataclass(frozen=True)
class SearchDoubt(Stage):
    """The search repair's doubt rule alone: depths a per-pixel search contradicts and the codes do not support
    dropped, nothing filled or replaced (repair.doubt_by_search; info repair). Needs inputs.valid."""

    name = "search_doubt"
    drops = "search_doubt"
    doubt_confidence: float

    def __call__(self, state: State) -> State:
        if state.inputs.valid is None:
            return state
        depth, info = doubt_by_search(state.depth, state.inputs, doubt_confidence=self.doubt_confidence)
        return state.replace(depth=depth, info={"repair": info})


@dataclass(frozen=True)
class Refine(Stage):
    """The photometric refinement: each pixel's depth moved by the offset within +- refine_range mm that best
    explains its window's images (pattern_model.refine_depth), skipped when refine_max_misfit > 0 and the pattern
    model's misfit at the depth is above it (the gate, compared once in pattern_model.refine_where_model_fits), and
    skipped without refine_through_halo when the patterns carry a lens halo (inputs.lens_halo > 0), and with
    refine_check kept only if it explains held-out frames better (pattern_model.refinement_generalises).
    info: refine_misfit, refined, refine_check, refine_skipped ("lens halo" or None)."""

    name = "refine"
    refine_range: float
    refine_max_misfit: float
    refine_check: bool
    refine_through_halo: bool

    def __call__(self, state: State) -> State:
        i = state.inputs
        if i.lens_halo > 0 and not self.refine_through_halo:
            # a lens with a halo is a real one, whose optics the model only approximates: there the refinement
            # fitted the model's errors (real captures 0-4: the held-out check refused it on every one)
            return state.replace(info={"refine_misfit": None, "refined": False, "refine_check": None,
                                       "refine_skipped": "lens halo"})
        # the images as the model holds them (on a GPU the renderer's tensors: no upload per use), the patterns
        # unblurred (the refinement fits its own blur)
        model = (i.camera, i.projector, i.images, i.raw_patterns, self.refine_range)
        refined, misfit = refine_where_model_fits(state.depth, *model, self.refine_max_misfit, device=i.device)
        info = {"refine_misfit": misfit, "refined": False, "refine_check": None, "refine_skipped": None}
        if refined is None:  # the model misses part of the optics there: refining would fit those errors
            return state.replace(info=info)
        if self.refine_check:
            info["refine_check"] = refinement_generalises(state.depth, *model, device=i.device)
        info["refined"] = info["refine_check"] is None or info["refine_check"]["keep"]
        return state.replace(depth=refined if info["refined"] else state.depth, info=info)


@dataclass(frozen=True)
class UniformFill(Stage):
    """Lit pixels without contrast (inside inputs.region) given the field's depth where the codes it predicts there
    are uniform and explain the images (fill.fill_uniform_codes), with that fit as their confidence; info
    filled_uniform."""

    name = "uniform_fill"
    marks = "filled"
    scores = True
    min_confidence: float

    def __call__(self, state: State) -> State:
        depth, fill_confidence, filled = fill_uniform_codes(state.depth, state.field_depth, state.inputs,
                                                            self.min_confidence)
        confidence = state.confidence
        if confidence is not None:
            confidence = np.where(filled, fill_confidence, confidence).astype(np.float32)
        return state.replace(depth=depth, confidence=confidence, info={"filled_uniform": int(filled.sum())})


@dataclass(frozen=True)
class RepairGrow(Stage):
    """The search repair's changes (fate "repaired") spread to neighbours that kept another surface's depth where
    the codes fit the repaired surface better (repair.grow_repair); nothing dropped or filled. info repair_grown."""

    name = "repair_grow"
    marks = "repaired"
    after = ("search_repair",)

    def __call__(self, state: State) -> State:
        if state.inputs.valid is None:
            return state.replace(info={"repair_grown": 0})
        depth, grown = grow_repair(state.depth, state.fate == FATE["repaired"], state.inputs)
        return state.replace(depth=depth, info={"repair_grown": int(grown.sum())})


@dataclass(frozen=True)
class StepSplit(Stage):
    """Each pixel between two surfaces along an image axis (lines fitted to the depths step_split_radius to
    step_split_radius + 16 pixels away on each side disagree at it by more than edge_filter pixel footprints) takes
    the side line whose codes fit its window best, where that fit is at most step_split_margin times the map's own
    (steps.split_ramps): the ramps a smooth field draws across a step a few projector rows deep. info step_split
    (pixels switched). Does nothing without edge_filter."""

    name = "step_split"
    marks = "split"
    step_split_radius: int
    step_split_margin: float
    edge_filter: float

    def __call__(self, state: State) -> State:
        if self.edge_filter <= 0 or self.step_split_radius <= 0:
            return state.replace(info={"step_split": 0})
        depth, switched = split_ramps(state.depth, state.inputs, self.step_split_radius, self.edge_filter,
                                      self.step_split_margin)
        return state.replace(depth=depth, info={"step_split": int(switched.sum())})


@dataclass(frozen=True)
class EdgeSide(Stage):
    """Each pixel with a depth across an edge (a jump above edge_filter pixel footprints within edge_side_radius
    pixels) keeps its depth, takes the one across or is dropped, as its codes fit them (edges.settle_edge_sides, with
    edge_side_margin); info edge_side (switched, dropped). Does nothing without edge_filter."""

    name = "edge_side"
    drops = "edge_side"
    marks = "repaired"
    edge_side_radius: int
    edge_side_margin: float
    edge_filter: float

    def __call__(self, state: State) -> State:
        if self.edge_filter <= 0:
            return state.replace(info={"edge_side": {"switched": 0, "dropped": 0}})
        depth, switched, dropped = settle_edge_sides(state.depth, state.inputs, self.edge_side_radius,
                                                     self.edge_side_margin, self.edge_filter)
        return state.replace(depth=depth, info={"edge_side": {"switched": int(switched.sum()),
                                                               "dropped": int(dropped.sum())}})


@dataclass(frozen=True)
class Denoise(Stage):
    """Each depth replaced by the value of a plane fitted over its (2 denoise_radius + 1)^2 window of depths within
    denoise_footprints pixel footprints of its own (surface.denoise_depth): the field's fine-scale noise; no pixel
    added or lost."""

    name = "denoise"
    denoise_radius: int
    denoise_footprints: float

    def __call__(self, state: State) -> State:
        i = state.inputs
        return state.replace(depth=denoise_depth(state.depth, i.camera, self.denoise_radius, self.denoise_footprints,
                                                 device=i.device))


@dataclass(frozen=True)
class HoleFill(Stage):
    """Pinholes closed: each pixel without depth inside inputs.valid with at least hole_fill of its 8 neighbours
    holding depths, all within hole_fill_footprints pixel footprints of the plane fitted to them, takes that plane's
    depth (surface.fill_pinholes); the runner scores their confidence. After the denoising, whose smooth depths
    make the plane check tight. info hole_filled."""

    name = "hole_fill"
    marks = "interpolated"
    hole_fill: int
    hole_fill_footprints: float

    def __call__(self, state: State) -> State:
        i = state.inputs
        depth, filled = fill_pinholes(state.depth, i.camera, i.valid, self.hole_fill, self.hole_fill_footprints)
        if not filled.any():
            return state.replace(info={"hole_filled": 0})
        return state.replace(depth=depth, info={"hole_filled": int(filled.sum())})


@dataclass(frozen=True)
class EdgeBand(Stage):
    """Last: the depths within edge_band_radius pixels of a depth edge of the field (a jump above edge_filter pixel
    footprints in state.field_depth; behind it, or with edge_band_sides "both" on either side:
    surface.edge_band_masks) kept only with a confidence of at least edge_band_confidence; behind an edge, within
    edge_band_far_radius pixels with edge_band_far_confidence where those are set (0: as in front). Fills and
    interpolations included, which is why it runs after them. Does nothing without edge_filter. info
    edge_band_dropped."""

    name = "edge_band"
    drops = "edge_band"
    after = ("depth", "confidence")
    edge_band_radius: int
    edge_band_confidence: float
    edge_band_sides: str
    edge_band_far_radius: int
    edge_band_far_confidence: float
    edge_filter: float

    def __call__(self, state: State) -> State:
        if self.edge_filter <= 0 or state.field_depth is None:
            return state.replace(info={"edge_band_dropped": 0})
        near_radius = self.edge_band_radius if self.edge_band_sides == "both" else 0
        near, far = edge_band_masks(state.field_depth, state.inputs.camera, near_radius,
                                    self.edge_band_far_radius or self.edge_band_radius, self.edge_filter,
                                    device=state.inputs.device)
        confidence = state.confidence
        weak_near = ~(confidence >= self.edge_band_confidence)
        weak_far = ~(confidence >= (self.edge_band_far_confidence or self.edge_band_confidence))
        drop = np.isfinite(state.depth) & ((near & weak_near) | (far & weak_far))
        if not drop.any():
            return state.replace(info={"edge_band_dropped": 0})
        depth = state.depth.copy()
        depth[drop] = np.nan
        return state.replace(depth=depth, info={"edge_band_dropped": int(drop.sum())})
