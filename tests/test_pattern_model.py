"""The rendering model's pattern blur and the photometric check of depth maps, on simulated scans whose
blur and depth are known."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from slwarp.neural.pattern_model import (blur_patterns, estimate_pattern_blur, fit_blur_by_projector_depth,
                                        least_squares_residual, photometric_filter, photometric_residual, refine_depth)
from slwarp.sim.simulate import SimOptions, simulate_scene


@pytest.fixture(scope="module")
def blurred_scan():
    """Small-rig plane scene with a depth-independent projector blur of 1.0 px and no noise."""
    opts = SimOptions(noise=False, bits=0, defocus_sigma=1.0, defocus_slope=0.0, shading=False, texture=False)
    return simulate_scene("steps", "random6", rig="small", options=opts, device="cpu")


def test_blur_patterns_matches_a_gaussian():
    p = torch.zeros(1, 41, 41)
    p[0, 20, 20] = 1.0
    out = blur_patterns(p, 1.5)[0].numpy()
    x = np.arange(41) - 20.0
    g = np.exp(-0.5 * (x / 1.5) ** 2)
    g /= g.sum()
    np.testing.assert_allclose(out, np.outer(g, g), atol=2e-4)  # the kernel is truncated at 3 sigma
    assert out.sum() == pytest.approx(1.0, abs=1e-5)
    assert blur_patterns(p, 0.0) is p


def test_estimated_blur_recovers_the_simulated_defocus(blurred_scan):
    s = blurred_scan
    sigma, mse = estimate_pattern_blur(s.camera, s.projector, s.images, s.patterns, s.gt_depth)
    assert sigma == pytest.approx(1.0, abs=0.25)  # measured 0.94 (bilinear sampling adds a little blur)
    assert min(mse.values()) < 0.5 * mse[0.0]  # the sharp model explains the images clearly worse
    # a depth map a few mm off (as from the depth search) barely moves the estimate
    sigma_off, _ = estimate_pattern_blur(s.camera, s.projector, s.images, s.patterns, s.gt_depth + 1.0)
    assert abs(sigma_off - sigma) <= 0.25


def test_photometric_filter_removes_wrong_depths_and_keeps_right_ones(blurred_scan):
    s = blurred_scan
    pats = blur_patterns(torch.as_tensor(s.patterns), 1.0).numpy()
    gt = s.gt_depth
    r = photometric_residual(gt, s.camera, s.projector, s.images, pats)
    ok = s.mask & np.isfinite(gt)
    # at the true depth the residual is mostly 0; it is not everywhere, because a and b come from the min and
    # max over only 6 frames (measured: median 0.0, 90th percentile 0.15)
    assert np.nanpercentile(r[ok], 50) < 0.02 and np.nanpercentile(r[ok], 90) < 0.2
    wrong = gt + 150.0  # as on the wrong side of an occlusion edge: the random codes no longer match
    kept_right = np.isfinite(photometric_filter(gt, s.camera, s.projector, s.images, pats))[ok].mean()
    kept_wrong = np.isfinite(photometric_filter(wrong, s.camera, s.projector, s.images, pats))[ok].mean()
    assert kept_right > 0.97 and kept_wrong < 0.15  # measured 0.98 and 0.10
    assert np.isnan(photometric_residual(np.full_like(gt, np.nan), s.camera, s.projector, s.images, pats)).all()


def test_least_squares_residual_fits_offset_and_modulation_per_pixel():
    rng = np.random.default_rng(0)
    codes = rng.uniform(0.2, 0.7, (6, 5))  # codes that never reach 0 or 1 (blur), as min/max cannot handle
    a, b = rng.uniform(0.0, 0.2, 5), rng.uniform(0.1, 0.8, 5)  # textured albedo: a and b differ per pixel
    images = a + b * codes
    np.testing.assert_allclose(least_squares_residual(images, codes, b), 0.0, atol=1e-12)  # ridge toward the true b
    # blurred binary codes (0.1 or 0.9, variance 0.16): max - min of the images is 0.8 b, a prior 20% low that
    # the ridge (0.02 against the variance 0.16) lets pull b down by 2%: residuals of 2% x 0.4 x b
    binary = np.stack([rng.permutation([0.1, 0.1, 0.1, 0.9, 0.9, 0.9]) for _ in range(5)], axis=1)
    images = a + b * binary
    r = least_squares_residual(images, binary, images.max(0) - images.min(0))
    assert 0.002 * b.max() < np.abs(r).max() < 0.012 * b.max()
    # codes running against the images: b is clamped at 0, the residual is the images' deviation from their mean
    r = least_squares_residual(0.9 - 0.5 * codes, codes, np.full(5, 0.5), ridge=0.0)
    np.testing.assert_allclose(r, (0.9 - 0.5 * codes) - (0.9 - 0.5 * codes).mean(0), atol=1e-12)


def test_blur_by_projector_depth_recovers_a_constant_defocus(blurred_scan):
    s = blurred_scan
    centres, sigmas = fit_blur_by_projector_depth(s.gt_depth, s.camera, s.projector, s.images, s.patterns)
    assert len(centres) == len(sigmas) > 1 and np.all(np.diff(centres) > 0)
    np.testing.assert_allclose(sigmas, 1.0, atol=0.25)  # as estimate_pattern_blur's global fit


def test_refine_depth_removes_a_smooth_depth_error(blurred_scan):
    s = blurred_scan
    ok = s.mask & np.isfinite(s.gt_depth)
    y, x = np.indices(s.gt_depth.shape)
    error = 0.8 + 0.4 * np.sin(x / 40.0) * np.cos(y / 30.0)  # mm, smooth over a 7x7 window, 0.4 to 1.2 mm
    start = np.where(ok, s.gt_depth + error, np.nan).astype(np.float32)
    start[::17, ::13] = np.nan  # holes stay holes
    refined = refine_depth(start, s.camera, s.projector, s.images, s.patterns, half_range_mm=1.5, step_mm=0.1)
    assert np.array_equal(np.isfinite(refined), np.isfinite(start))
    sel = np.isfinite(start)
    before = np.abs(start - s.gt_depth)[sel]
    after = np.abs(refined - s.gt_depth)[sel]
    assert np.median(before) > 0.7 and np.median(after) < 0.1
    with pytest.raises(ValueError, match="half_range_mm"):
        refine_depth(start, s.camera, s.projector, s.images, s.patterns, half_range_mm=0.0)
