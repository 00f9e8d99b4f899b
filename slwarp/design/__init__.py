"""Pattern design: projector patterns optimised for a rig through the differentiable image model.

    objective  the expected miss of each camera pixel's code comparison along its epipolar line, under the camera's
               offset, modulation, blur and noise (`CodeModel`, `miss_loss`)
    optimise   Adam on the pattern values, per-pixel codes spanning 0..1, the best by a fixed validation batch
               (`design_patterns`, `DesignOptions`, `DesignResult`)

The result is a `PatternSet` named design{K}_{i} (role {kind: designed, index: i, count: K}); slwarp.scans.pattern_files
writes it as projector-ready PNGs and a pattern-set file that `slwarp simulate --patterns` and `slwarp reconstruct
--patterns` read. `slwarp design-patterns` (slwarp.cli.design) is the command.
"""
from .objective import CodeModel, NoiseModel, code_image, epipolar_direction, epipolar_span_px, miss_loss
from .optimise import DesignOptions, DesignResult, binarise, design_patterns, evaluate_patterns, normalised_codes

__all__ = ["CodeModel", "NoiseModel", "code_image", "epipolar_direction", "epipolar_span_px", "miss_loss", "DesignOptions", "DesignResult", "binarise",
           "design_patterns", "evaluate_patterns", "normalised_codes"]
