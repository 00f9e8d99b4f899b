"""The rendering model's pattern blur and the photometric check of depth maps, on simulated scans whose
blur and depth are known."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from slwarp.neural.pattern_model import blur_patterns, estimate_pattern_blur, photometric_filter, photometric_residual
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
