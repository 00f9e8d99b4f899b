"""The pattern model: what a camera pixel sees when the projector shows pattern P_i.

    I_i(r) = a(r) + b(r) P_i(pi(x))

x is the surface point seen by camera pixel r (camera frame, mm), pi(x) its projector pixel (OpenCV
distortion included), P_i the pattern as the camera sees it (Gaussian-blurred by `pattern_blur`
projector px: projector defocus and the camera pixel's footprint), a(r) = min_i I_i(r) the offset
(ambient light) and b(r) = max_i I_i(r) - a(r) the modulation. A pixel takes part (in training, the depth
search and the blur fit) when it is lit with contrast: b(r) > CONTRAST_THRESHOLD.

This package holds that model for the host side (numpy, OpenCV) and the pattern blur (torch):
- `image`: offset and modulation (also by least squares), the contrast test, the blur, projector coordinates of a
  depth map and the patterns sampled there;
- `residual`: the photometric residual of a depth map (on the host or on a device), its filter and the photometric
  confidence;
- `blur`: the fit of the blur, one sigma (the training's start) or one per projector depth;
- `halo`: the lens halo's share fitted to a scan (`fit_halo`);
- `refine`: the photometric refinement of a depth map (`refine_depth`), the model's misfit and the held-out check.
The refinement and its blur fit per projector depth run in torch on any device (numpy in and out). The fused
renderer evaluates the same model per sample in Warp (slwarp.kernels.render) and its twin in torch
(slwarp.neural.ops.twin).
"""
from .blur import (BLUR_BINS, BLUR_FIT_PIXELS, BLUR_LADDER, BLUR_LADDER_STEP, estimate_pattern_blur,
                   fit_blur_by_projector_depth)
from .image import (CONTRAST_THRESHOLD, LS_RIDGE, MIN_MODULATION, OFF_IMAGE_PX, blur_patterns,
                    least_squares_offset_modulation, least_squares_residual, lit_with_contrast, offset_and_modulation,
                    predicted_intensities, projector_coords, projector_coords_at, projector_coords_of, sample_patterns,
                    sample_patterns_at, with_halo)
from .halo import HALO_SHARES, HALO_SIGMA, fit_halo, halo_light
from .refine import (REFINE_RADIUS, REFINE_STEP_MM, model_misfit, refine_depth, refine_where_model_fits,
                     refinement_generalises)
from .residual import photometric_confidence, photometric_filter, photometric_residual, residual_at

__all__ = [
    "CONTRAST_THRESHOLD",
    "OFF_IMAGE_PX",
    "MIN_MODULATION",
    "LS_RIDGE",
    "offset_and_modulation",
    "lit_with_contrast",
    "blur_patterns",
    "with_halo",
    "fit_halo",
    "halo_light",
    "HALO_SHARES",
    "HALO_SIGMA",
    "projector_coords",
    "projector_coords_at",
    "projector_coords_of",
    "sample_patterns",
    "sample_patterns_at",
    "predicted_intensities",
    "least_squares_residual",
    "least_squares_offset_modulation",
    "photometric_residual",
    "residual_at",
    "photometric_filter",
    "photometric_confidence",
    "BLUR_FIT_PIXELS",
    "BLUR_LADDER_STEP",
    "BLUR_LADDER",
    "BLUR_BINS",
    "estimate_pattern_blur",
    "fit_blur_by_projector_depth",
    "REFINE_RADIUS",
    "REFINE_STEP_MM",
    "model_misfit",
    "refine_where_model_fits",
    "refine_depth",
    "refinement_generalises",
]
