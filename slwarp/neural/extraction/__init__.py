"""From a trained field to a depth map: the extraction, as an ordered list of stages.

A config's `extraction.stages` names the stages in the order they run (config.ExtractionConfig; the presets' lists,
`--stages`); `extract_depth` builds them (`build_stages`) and runs them on one `State` (`run_stages`), which times
each, records the fate of the pixels it changed and scores the confidence of its new depths the same way for all.
A new stage is one subclass of `stages.Stage` (its settings: extraction options by their flat names) named in a list.

- `state`: the pattern model's inputs bundled once (`ModelInputs`), the trained field (`TrainedField`), the `State`
  a stage takes and returns, the pixel fates (`PIXEL_FATES`, `fate_counts`) and the result (`Extraction`).
- `stages`: the stages (`STAGES` by name) and their base class.
- `runner`: `build_stages`, `run_stages`, `extract_depth`.
- `surface`: marching cubes, the mesh's depth by ray casting or the field's by sphere tracing, the flying-pixel
  filter and its edge readmission, the edge-aware denoising, point clouds.
- `confidence`: per-pixel confidence maps of a depth map (the photometric term, which the training shares, is
  `slwarp.neural.pattern_model`'s).
- `repair`: the search repair, its doubt rule and its growth; `fill`: the uniform-code fill; `edges`: the pixels beside
  a depth edge settled by their codes; `steps`: the ramps a smooth field draws across a small depth step split into
  the two surfaces.
"""
from .runner import build_stages, extract_depth, run_stages
from .stages import STAGES, Stage
from .state import (FATE, PIXEL_FATES, Extraction, ModelInputs, State, TrainedField, fate_counts, pixel_fates,
                    register_fate)

__all__ = ["build_stages", "extract_depth", "run_stages", "STAGES", "Stage", "FATE", "PIXEL_FATES", "Extraction",
           "ModelInputs", "State", "TrainedField", "fate_counts", "pixel_fates", "register_fate"]
