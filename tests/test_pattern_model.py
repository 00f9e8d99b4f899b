"""The rendering model's pattern blur and the photometric check of depth maps, on simulated scans whose
blur and depth are known."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from slwarp.neural.config import REFINE_MAX_MISFIT
from slwarp.neural.pattern_model import (BLUR_BINS, BLUR_LADDER, BLUR_LADDER_STEP, MIN_MODULATION, blur_patterns,
                                        estimate_pattern_blur, fit_blur_by_projector_depth, least_squares_residual,
                                        lit_with_contrast, offset_and_modulation, photometric_filter,
                                        photometric_residual, projector_coords, refine_depth, sample_patterns,
                                        refinement_generalises, model_misfit, refine_where_model_fits, REFINE_RADIUS,
                                        REFINE_STEP_MM)
from slwarp.neural.pattern_model.blur import _BlurLadder
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


def test_photometric_residual_of_a_sparse_map_equals_the_dense_one(blurred_scan, monkeypatch):
    """A map with depth at few pixels takes the sparse path (those pixels only): the same values as the dense
    computation, with depths off the projector and more pixels than one remap row holds."""
    from slwarp.neural.pattern_model import image, residual

    s = blurred_scan
    pats = blur_patterns(torch.as_tensor(s.patterns), 1.0).numpy()
    rng = np.random.default_rng(1)
    depth = np.where(rng.random(s.gt_depth.shape) < 0.2, s.gt_depth + rng.normal(0, 20, s.gt_depth.shape), np.nan)
    depth[0, :5] = 1.0  # in front of the projector's near range: projects far off its image
    depth = depth.astype(np.float32)
    assert 0.15 < np.isfinite(depth).mean() < residual.SPARSE_SHARE
    assert np.isfinite(depth).sum() > image._REMAP_ROW
    sparse = photometric_residual(depth, s.camera, s.projector, s.images, pats)
    monkeypatch.setattr(residual, "SPARSE_SHARE", 0.0)  # the dense path
    dense = photometric_residual(depth, s.camera, s.projector, s.images, pats)
    np.testing.assert_array_equal(np.isfinite(sparse), np.isfinite(depth))
    np.testing.assert_allclose(sparse, dense, rtol=1e-6, atol=1e-7)
    assert np.isnan(photometric_residual(np.full_like(depth, np.nan), s.camera, s.projector, s.images, pats)).all()


def test_patterns_sampled_on_a_device_equal_cv2_remap():
    """twin.bilinear_patterns, which the residual on a device samples with, has sample_patterns_at's conventions (pixel centres at integer coordinates, zeros
    outside, bilinear): equal at coordinates on OpenCV 4's 1/32 px grid, edges and outside included."""
    from slwarp.neural.pattern_model import sample_patterns_at
    from slwarp.neural.ops.twin import bilinear_patterns

    rng = np.random.default_rng(2)
    pats = rng.uniform(0.0, 1.0, (3, 12, 17)).astype(np.float32)
    uv = (np.round(rng.uniform(-2.0, 19.0, (500, 2)) * 32) / 32).astype(np.float32)
    uv[:5] = [[-0.5, 0.0], [16.5, 11.5], [-1.0, -1.0], [16.0, 11.0], [-10.0, -10.0]]
    got = bilinear_patterns(torch.as_tensor(pats), torch.as_tensor(uv)).t().numpy()
    np.testing.assert_allclose(got, sample_patterns_at(pats, uv), atol=2e-6)


@pytest.mark.parametrize("share", [1.0, 0.1])
def test_photometric_residual_on_a_device_equals_the_host_path(blurred_scan, share):
    """With tensors (here on the CPU; the extraction passes its GPU's) the residual is computed by torch on their
    device: the host path's values within a float's rounding (OpenCV 5's remap; OpenCV 4 rounds projector
    coordinates to 1/32 px first), NaN at the same pixels, dense and sparse maps alike."""
    import cv2

    s = blurred_scan
    pats = blur_patterns(torch.as_tensor(s.patterns), 1.0).numpy()
    rng = np.random.default_rng(4)
    depth = np.where(rng.random(s.gt_depth.shape) < share, s.gt_depth + rng.normal(0, 2, s.gt_depth.shape), np.nan)
    depth[0, :5] = 1.0  # projects far off the projector's image
    depth = depth.astype(np.float32)
    host = photometric_residual(depth, s.camera, s.projector, s.images, pats)
    device = photometric_residual(depth, s.camera, s.projector, torch.as_tensor(s.images), torch.as_tensor(pats))
    np.testing.assert_array_equal(np.isfinite(device), np.isfinite(host))
    np.testing.assert_allclose(device, host, rtol=0, atol=1e-6 if int(cv2.__version__.split(".")[0]) >= 5 else 2e-2)


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
    start = _smooth_error_start(s)
    refined = refine_depth(start, s.camera, s.projector, s.images, s.patterns, half_range_mm=1.5, step_mm=0.1)
    assert np.array_equal(np.isfinite(refined), np.isfinite(start))
    sel = np.isfinite(start)
    before = np.abs(start - s.gt_depth)[sel]
    after = np.abs(refined - s.gt_depth)[sel]
    assert np.median(before) > 0.7 and np.median(after) < 0.1
    with pytest.raises(ValueError, match="half_range_mm"):
        refine_depth(start, s.camera, s.projector, s.images, s.patterns, half_range_mm=0.0)



def test_refinement_check_keeps_a_refinement_that_removes_a_smooth_error(blurred_scan):
    """A depth 0.4 to 1.2 mm behind the surface: refined without each frame in turn, every held-out frame is
    explained better, so the refinement is kept."""
    import functools

    s = blurred_scan
    start = _smooth_error_start(s)
    coarse = functools.partial(refine_depth, step_mm=0.1)
    check = refinement_generalises(start, s.camera, s.projector, s.images, s.patterns, 1.5, refine=coarse)
    assert check["keep"]
    assert len(check["before"]) == len(check["after"]) == len(s.images)
    assert all(a < b for a, b in zip(check["after"], check["before"]))


def test_refinement_check_refuses_a_refinement_that_moves_away_from_the_surface(blurred_scan):
    """The check scores what a refinement did, not that it ran: one that moves the true depth 1 mm off is
    refused (every held-out frame explained worse); one that brings a 1 mm error back to the truth is kept;
    with fewer than 3 frames there is nothing to hold out."""
    s = blurred_scan
    gt = np.where(s.mask, s.gt_depth, np.nan).astype(np.float32)
    args = (s.camera, s.projector, s.images, s.patterns, 3.0)
    away = refinement_generalises(gt, *args, refine=lambda d, *a, **k: d + 1.0)
    assert not away["keep"] and all(a > b for a, b in zip(away["after"], away["before"]))
    back = refinement_generalises(gt + 1.0, *args, refine=lambda d, *a, **k: gt)
    assert back["keep"] and all(a < b for a, b in zip(back["after"], back["before"]))
    two = refinement_generalises(gt, s.camera, s.projector, s.images[:2], s.patterns[:2], 3.0)
    assert two["keep"] and two["before"] == []


def test_model_misfit_separates_a_linear_camera_from_a_gamma_camera_and_grows_off_the_surface():
    """At the true depth of the same scene (small rig, noise and texture on), a linear camera's images sit below the
    defaults' refinement limit and a gamma-2.2 camera's above it; 1.5 mm off the surface the misfit grows; too few
    pixels with depth give NaN."""
    scans = {g: simulate_scene("spheres", "random6", rig="small", options=SimOptions(seed=0, gamma=g), device="cpu")
             for g in (1.0, 2.2)}
    misfit = {}
    for g, s in scans.items():
        gt = np.where(s.mask, s.gt_depth, np.nan).astype(np.float32)
        misfit[g] = model_misfit(gt, s.camera, s.projector, s.images[:6], s.patterns[:6])
    assert misfit[1.0] < REFINE_MAX_MISFIT < misfit[2.2]
    s = scans[1.0]
    gt = np.where(s.mask, s.gt_depth, np.nan).astype(np.float32)
    # (the blur fit absorbs part of a depth error: 0.017 -> 0.022 at 1.5 mm, so a field's small errors do not trip it)
    assert model_misfit(gt + 1.5, s.camera, s.projector, s.images[:6], s.patterns[:6]) > 1.2 * misfit[1.0]
    few = np.full_like(gt, np.nan)
    few[:5, :5] = gt[100:105, 100:105]
    assert np.isnan(model_misfit(few, s.camera, s.projector, s.images[:6], s.patterns[:6]))


def test_refine_where_model_fits_refines_as_refine_depth_or_leaves_the_depth(blurred_scan):
    """One model fit for both: under the limit (or with no limit) the result is refine_depth's exactly, with
    model_misfit's value (None without a limit); over it no refinement (None) comes back, with the misfit."""
    s = blurred_scan
    start = _smooth_error_start(s)
    args = (s.camera, s.projector, s.images, s.patterns)
    refined = refine_depth(start, *args, 1.5)
    misfit = model_misfit(start, *args)
    for limit, want, want_misfit in ((1.0, refined, misfit), (0.0, refined, None), (misfit / 2, None, misfit)):
        got, got_misfit = refine_where_model_fits(start, *args, 1.5, limit)
        if want is None:
            assert got is None
        else:
            np.testing.assert_array_equal(got, want)
        assert got_misfit == want_misfit
    with pytest.raises(ValueError, match="half_range_mm and step_mm must be > 0"):
        refine_where_model_fits(start, *args, 0.0, 1.0)


def test_blur_ladder_samples_as_cv2_remap():
    """The torch ladder's bilinear sampling has cv2.remap's conventions (pixel centres at integer coordinates,
    zeros outside, linear between rungs): equal at coordinates on cv2's 1/32 px grid, edges and outside included."""
    rng = np.random.default_rng(1)
    pats = rng.uniform(0.0, 1.0, (3, 12, 17)).astype(np.float32)
    ladder = _BlurLadder(pats, "cpu")
    uv = (np.round(rng.uniform(-2.0, 19.0, (9, 11, 2)) * 32) / 32).astype(np.float32)
    uv[0, :3] = [[-0.5, 0.0], [16.5, 11.5], [-1.0, -1.0]]
    sigma = rng.uniform(0.0, 2.6, (9, 11)).astype(np.float32)
    got = ladder.sample(torch.as_tensor(uv), ladder.position(torch.as_tensor(sigma))).numpy()
    np.testing.assert_allclose(got, _RefBlurLadder(pats).sample(uv, sigma), atol=2e-6)


def _smooth_error_start(s):
    ok = s.mask & np.isfinite(s.gt_depth)
    y, x = np.indices(s.gt_depth.shape)
    error = 0.8 + 0.4 * np.sin(x / 40.0) * np.cos(y / 30.0)  # mm, smooth over a 7x7 window, 0.4 to 1.2 mm
    start = np.where(ok, s.gt_depth + error, np.nan).astype(np.float32)
    start[::17, ::13] = np.nan  # holes stay holes
    return start


def test_refine_depth_matches_the_numpy_reference(blurred_scan):
    """The torch refinement against the host one it replaced: the same blur fit and the same depths, but at a
    few pixels where cv2.remap's 1/32 px rounding of the projector coordinates tips the argmin (measured:
    median difference 0, 99th percentile 0.0003 mm, max 0.05 mm; the MAE against the truth equal to 1e-6 mm)."""
    s = blurred_scan
    start = _smooth_error_start(s)
    c_ref, s_ref = _ref_fit_blur(start, s.camera, s.projector, s.images, s.patterns)
    c_new, s_new = fit_blur_by_projector_depth(start, s.camera, s.projector, s.images, s.patterns)
    np.testing.assert_allclose(c_new, c_ref, atol=1e-4)
    np.testing.assert_allclose(s_new, s_ref, atol=1e-4)
    ref = _ref_refine_depth(start, s.camera, s.projector, s.images, s.patterns, half_range_mm=1.5, step_mm=0.1)
    new = refine_depth(start, s.camera, s.projector, s.images, s.patterns, half_range_mm=1.5, step_mm=0.1, chunk=5)
    assert np.array_equal(np.isfinite(new), np.isfinite(ref))
    sel = np.isfinite(ref)
    diff = np.abs(new - ref)[sel]
    assert np.median(diff) < 1e-4 and np.percentile(diff, 99) < 0.005 and diff.max() < 0.2
    mae_ref, mae_new = (np.abs(d - s.gt_depth)[sel].mean() for d in (ref, new))
    assert abs(mae_new - mae_ref) < 1e-3
    # the offsets in chunks: the running argmin is that of the sequential scan
    one = refine_depth(start, s.camera, s.projector, s.images, s.patterns, half_range_mm=1.5, step_mm=0.1, chunk=1)
    np.testing.assert_allclose(one, new, atol=1e-5, equal_nan=True)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_refine_depth_on_cuda_matches_the_cpu():
    # simulated on CUDA: a GPU machine need not have Warp's CPU compiler
    opts = SimOptions(noise=False, bits=0, defocus_sigma=1.0, defocus_slope=0.0, shading=False, texture=False)
    s = simulate_scene("steps", "random6", rig="small", options=opts, device="cuda")
    start = _smooth_error_start(s)
    cpu = refine_depth(start, s.camera, s.projector, s.images, s.patterns, half_range_mm=1.5, step_mm=0.1)
    gpu = refine_depth(start, s.camera, s.projector, s.images, s.patterns, half_range_mm=1.5, step_mm=0.1, device="cuda")
    assert np.array_equal(np.isfinite(gpu), np.isfinite(cpu))
    diff = np.abs(gpu - cpu)[np.isfinite(cpu)]
    assert np.median(diff) < 1e-4 and np.percentile(diff, 99) < 0.005
    sel = np.isfinite(cpu)
    assert abs(np.abs(gpu - s.gt_depth)[sel].mean() - np.abs(cpu - s.gt_depth)[sel].mean()) < 1e-3


# ------------------------------------------------------------------------------------------------------------------
# The reference: the host implementation of the refinement (numpy, cv2.remap) that the torch one in
# slwarp.neural.pattern_model replaced, kept as it was to check that the port computes the same thing.

def _ref_projector_depth(depth: np.ndarray, camera, projector) -> np.ndarray:
    rays = camera.pixel_to_ray(camera.pixel_grid())
    with np.errstate(invalid="ignore"):
        X = rays * (np.asarray(depth, np.float64) / rays[..., 2])[..., None]
    return np.asarray(projector.camera_to_projector(X.reshape(-1, 3)), np.float64)[:, 2].reshape(depth.shape)


class _RefBlurLadder:

    def __init__(self, patterns: np.ndarray):
        pats = torch.as_tensor(np.asarray(patterns, np.float32))
        self.rungs = [blur_patterns(pats, float(s)).numpy() for s in BLUR_LADDER]

    def sample(self, uv: np.ndarray, sigma: np.ndarray) -> np.ndarray:
        """[N, H, W] at projector pixels uv [H, W, 2] with blur sigma [H, W] (px)."""
        pos = np.clip(sigma / BLUR_LADDER_STEP, 0, len(self.rungs) - 1 - 1e-6)
        lo = np.floor(pos).astype(np.int64)
        t = (pos - lo).astype(np.float32)
        out = 0.0
        for rung in np.unique(np.concatenate([np.unique(lo), np.unique(lo) + 1])):
            w = np.where(lo == rung, 1 - t, 0) + np.where(lo + 1 == rung, t, 0)
            if w.any():
                out = out + w * sample_patterns(self.rungs[rung], uv)
        return np.asarray(out, np.float32)


def _ref_fit_blur(depth: np.ndarray, camera, projector, images: np.ndarray, patterns: np.ndarray,
                  bins: int = BLUR_BINS) -> tuple[np.ndarray, np.ndarray]:
    images = np.asarray(images, np.float32)
    _, b = offset_and_modulation(images)
    ok = np.isfinite(depth) & lit_with_contrast(b)
    if ok.sum() < 100:
        raise ValueError(f"fit_blur_by_projector_depth: only {int(ok.sum())} pixels with depth and contrast")
    bins = int(max(1, min(bins, ok.sum() // 200)))
    zp = _ref_projector_depth(np.where(ok, depth, np.nan), camera, projector)[ok]
    edges = np.quantile(zp, np.linspace(0.0, 1.0, bins + 1))
    which = np.clip(np.searchsorted(edges, zp, side="right") - 1, 0, bins - 1)
    uv = projector_coords(np.where(ok, depth, np.nan), camera, projector)
    pats = torch.as_tensor(np.asarray(patterns, np.float32))
    mse = np.empty((len(BLUR_LADDER), bins))
    for j, s in enumerate(BLUR_LADDER):
        r = least_squares_residual(images[:, ok], sample_patterns(blur_patterns(pats, float(s)).numpy(), uv)[:, ok], b[ok])
        mse[j] = np.bincount(which, (r**2).mean(0), bins) / np.maximum(np.bincount(which, minlength=bins), 1)
    sigma = np.empty(bins)
    for k in range(bins):
        j = int(np.argmin(mse[:, k]))
        sigma[k] = BLUR_LADDER[j]
        if 0 < j < len(BLUR_LADDER) - 1:
            den = mse[j - 1, k] - 2 * mse[j, k] + mse[j + 1, k]
            if den > 0:
                sigma[k] += 0.5 * BLUR_LADDER_STEP * (mse[j - 1, k] - mse[j + 1, k]) / den
    centres = np.array([np.median(zp[which == k]) for k in range(bins)])
    return centres, sigma


def _ref_refine_depth(depth: np.ndarray, camera, projector, images: np.ndarray, patterns: np.ndarray,
                      half_range_mm: float, radius: int = REFINE_RADIUS, step_mm: float = REFINE_STEP_MM) -> np.ndarray:
    if not half_range_mm > 0 or not step_mm > 0:
        raise ValueError(f"refine_depth: half_range_mm and step_mm must be > 0, got {half_range_mm}, {step_mm}")
    depth = np.asarray(depth, np.float32)
    ok = np.isfinite(depth)
    if not ok.any():
        return depth.copy()
    import cv2

    images = np.asarray(images, np.float32)
    _, b = offset_and_modulation(images)
    centres, sigmas = _ref_fit_blur(depth, camera, projector, images, patterns)
    sigma = np.interp(np.nan_to_num(_ref_projector_depth(depth, camera, projector), nan=float(centres[0])), centres, sigmas)
    ladder = _RefBlurLadder(patterns)
    deltas = np.arange(-half_range_mm, half_range_mm + 1e-9, step_mm)
    k = 2 * radius + 1
    # running argmin with the costs on either side of the best offset (for the parabola): O(H W) memory
    best = np.full(depth.shape, np.inf, np.float32)
    best_j = np.zeros(depth.shape, np.int64)
    left = np.full(depth.shape, np.nan, np.float32)
    right = np.full(depth.shape, np.nan, np.float32)
    prev = np.full(depth.shape, np.nan, np.float32)
    for j, delta in enumerate(deltas):
        shifted = np.where(ok, depth + np.float32(delta), np.nan)
        codes = ladder.sample(projector_coords(shifted, camera, projector), sigma)
        r = least_squares_residual(images, codes, b)
        cost = np.where(ok, np.abs(r).mean(0) / np.maximum(b, MIN_MODULATION), 0.0).astype(np.float32)
        cost = cv2.boxFilter(cost, -1, (k, k), normalize=False, borderType=cv2.BORDER_CONSTANT)
        right = np.where(best_j == j - 1, cost, right)
        better = cost < best
        best = np.where(better, cost, best)
        best_j = np.where(better, j, best_j)
        left = np.where(better, prev, left)
        right = np.where(better, np.nan, right)
        prev = cost
    den = left - 2 * best + right
    inner = np.isfinite(den) & (den > 0)
    frac = np.where(inner, 0.5 * (left - right) / np.where(inner, den, 1.0), 0.0)
    offset = deltas[best_j] + step_mm * frac
    return np.where(ok, depth + offset, np.nan).astype(np.float32)


def test_fill_uniform_codes_gives_the_field_depth_to_lit_pixels_without_contrast(blurred_scan):
    """Pixels lit by a projector square that is black or white in all 6 patterns have no contrast: they take the
    field's depth where the codes predicted there are uniform and explain the images; a field 30 mm off predicts
    other codes there and fills far fewer; nothing is filled outside `region` or where the pixel has depth."""
    from slwarp.neural.extraction.fill import fill_uniform_codes
    from slwarp.neural.extraction.state import ModelInputs

    s = blurred_scan
    pats = blur_patterns(torch.as_tensor(s.patterns), 1.0).numpy()
    _, b = offset_and_modulation(s.images)
    lit = lit_with_contrast(b)
    gt = np.where(s.mask, s.gt_depth, np.nan).astype(np.float32)
    field = np.nan_to_num(s.gt_depth, nan=np.inf).astype(np.float32)  # the field's depth: exact where it hits
    depth = np.where(lit, gt, np.nan).astype(np.float32)
    inputs = ModelInputs(s.camera, s.projector, s.images, pats, s.depth_range, lit=lit)
    out, conf, filled = fill_uniform_codes(depth, field, inputs, 0.6)
    dark = s.mask & ~lit  # lit by the projector (GT mask) but without contrast
    assert dark.sum() > 50
    assert filled.sum() > 0.5 * dark.sum()
    # a shadow predicts all-black codes now and then (measured: 17 of 559 fills), at the surface's depth
    assert (filled & ~s.mask).sum() < 0.05 * filled.sum()
    assert not (filled & lit).any()
    np.testing.assert_allclose(out[filled], s.gt_depth[filled], atol=0.05)  # exact neighbours: no correction
    np.testing.assert_array_equal(out[~filled], depth[~filled])
    assert np.isfinite(conf[filled]).all() and (conf[filled] >= 0.6).all() and np.isnan(conf[~filled]).all()
    _, _, off = fill_uniform_codes(depth, field + 30.0, inputs, 0.6)
    assert off.sum() < 0.2 * filled.sum()
    nowhere = ModelInputs(s.camera, s.projector, s.images, pats, s.depth_range, lit=lit, region=np.zeros_like(lit))
    assert not fill_uniform_codes(depth, field, nowhere, 0.6)[2].any()


def test_fill_uniform_codes_corrects_by_the_refinement_offset_and_ignores_repairs(blurred_scan):
    """A field 1 mm behind the surface: the fills take its depth shifted by the neighbours' depth - field_depth
    (here -1 mm), and neighbours that a search repair moved far off (-80 mm) do not enter that mean."""
    from slwarp.neural.extraction.fill import fill_uniform_codes
    from slwarp.neural.extraction.state import ModelInputs

    s = blurred_scan
    pats = blur_patterns(torch.as_tensor(s.patterns), 1.0).numpy()
    _, b = offset_and_modulation(s.images)
    lit = lit_with_contrast(b)
    gt = np.where(s.mask, s.gt_depth, np.nan).astype(np.float32)
    field = np.nan_to_num(s.gt_depth, nan=np.inf).astype(np.float32) + 1.0
    depth = np.where(lit, gt, np.nan).astype(np.float32)
    repaired = lit & (np.arange(lit.shape[1])[None, :] % 5 == 0)
    depth[repaired] -= 80.0
    inputs = ModelInputs(s.camera, s.projector, s.images, pats, s.depth_range, lit=lit)
    out, _, filled = fill_uniform_codes(depth, field, inputs, 0.6)
    on = filled & s.mask
    assert on.sum() > 50
    assert np.nanmedian(np.abs(out[on] - s.gt_depth[on])) < 0.05
    assert np.mean(np.abs(out[on] - s.gt_depth[on]) < 0.2) > 0.95


def test_with_halo_spreads_a_share_of_the_light_and_keeps_the_mean():
    """with_halo: (1 - share) x the pattern + share x its wide blur: an edge keeps its step of 1 - share, the dark
    side rises towards the bright one over about sigma, the mean light stays; share 0 is the pattern itself."""
    from slwarp.neural.pattern_model import with_halo

    p = np.zeros((2, 120, 200), np.float32)
    p[:, :, 100:] = 1.0
    h = with_halo(p, 0.1, 20.0)
    row = h[0, 60]
    assert abs((row[100] - row[99]) - 0.9) < 0.02  # the sharp step that is left
    assert 0.04 < row[99] < 0.06 and row[0] < 0.01 and 0.99 < row[-1] <= 1.0  # the halo near the edge, not far away
    assert np.all(np.diff(row) >= -1e-6) and abs(h.mean() - p.mean()) < 1e-3
    assert np.array_equal(with_halo(p, 0.0, 20.0), p)


def test_trainer_sees_the_patterns_through_the_configured_halo():
    """sampling.pattern_halo: the trainer's scan (search, renderer, extraction) holds the patterns with the halo;
    without it, the scan itself (a fitted halo: tests/test_lens_halo.py)."""
    from slwarp.neural.pattern_model import with_halo
    from slwarp.neural.training import Trainer
    from slwarp.neural.training.trainer import seen_through_lens
    from slwarp.neural.config import preset
    from slwarp.sim.simulate import SimOptions, simulate_scene

    scan = simulate_scene("spheres", "gray4", rig="small", options=SimOptions(seed=0), device="cpu")
    assert seen_through_lens(scan, 0.0, 10.0) is scan
    seen = seen_through_lens(scan, 0.1, 10.0)
    np.testing.assert_allclose(seen.patterns, with_halo(scan.patterns, 0.1, 10.0))
    assert np.array_equal(seen.images, scan.images) and seen.names == scan.names
    assert not np.array_equal(seen.patterns, scan.patterns)
    trainer = Trainer(scan, preset("tiny", device="cpu", pattern_halo=0.1, pattern_halo_sigma=10.0), progress=False)
    np.testing.assert_allclose(trainer.scan.patterns, seen.patterns)


def _blur_fit_inputs(s):
    """The tensors blur._fit_blur takes, for a scan on the CPU."""
    from slwarp.neural.pattern_model.blur import _rays_in_projector
    from slwarp.neural.pattern_model.image import lit_with_contrast, offset_and_modulation

    d = torch.as_tensor(np.asarray(s.gt_depth, np.float32))
    img = torch.as_tensor(np.asarray(s.images, np.float32))
    _, b = offset_and_modulation(img)
    ok = torch.isfinite(d) & lit_with_contrast(b)
    return d, ok, _rays_in_projector(s.camera, s.projector, "cpu"), img, b


def test_blur_fit_leaves_out_pixels_without_a_finite_ray_or_a_depth_in_front(blurred_scan):
    from types import SimpleNamespace

    from slwarp.neural.pattern_model.blur import _fit_blur

    s = blurred_scan
    d, ok, rays, img, b = _blur_fit_inputs(s)
    ladder = _BlurLadder(s.patterns, "cpu")
    z0, s0 = _fit_blur(d, ok, rays, s.projector, img, b, ladder, BLUR_BINS)
    # a tenth of the rows without a finite ray, and as many pixels at depth 0 (a NaN projector depth made every
    # bin edge NaN, equal depths made equal edges: either left bins empty and the fit raised)
    ray = rays.ray.clone()
    ray[: ray.shape[0] // 10] = float("nan")
    d2 = d.clone()
    d2[-(d.shape[0] // 10):] = 0.0
    z1, s1 = _fit_blur(d2, ok, SimpleNamespace(ray=ray, T=rays.T), s.projector, img, b, ladder, BLUR_BINS)
    assert len(z1) == len(s1) == len(z0) and torch.all(torch.diff(z1) > 0)
    np.testing.assert_allclose(s1.numpy(), 1.0, atol=0.25)
    np.testing.assert_allclose(s0.numpy(), 1.0, atol=0.25)


def test_blur_fit_gives_one_sigma_per_bin_that_holds_pixels(blurred_scan):
    from types import SimpleNamespace

    from slwarp.neural.pattern_model.blur import _fit_blur

    s = blurred_scan
    d, ok, rays, img, b = _blur_fit_inputs(s)
    # every ray with the same projector z per unit depth, and two depths: two projector depths over 6 bins
    ray = rays.ray.clone()
    ray[..., 2] = 1.0
    d2 = torch.where(torch.arange(d.shape[1])[None, :] < d.shape[1] // 2, 700.0, 900.0).expand_as(d).contiguous()
    z, sig = _fit_blur(d2, ok, SimpleNamespace(ray=ray, T=rays.T), s.projector, img, b, _BlurLadder(s.patterns, "cpu"),
                       BLUR_BINS)
    assert 1 <= len(z) == len(sig) < BLUR_BINS
    assert torch.all(torch.diff(z) > 0) and torch.all(torch.isfinite(sig))
