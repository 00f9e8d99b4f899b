"""The ramps across a depth step split into the two surfaces (slwarp.neural.extraction.steps.split_ramps): the side
lines, a ramp drawn across the boxes' steps mostly given back to its surfaces, the right map left alone, the same
result on every device, and the stage in fast's and accurate's lists through its switch, step_split_radius."""
import cv2
import numpy as np
import pytest
import torch

from slwarp.evaluation.metrics import depth_step_distance
from slwarp.neural.config import preset
from slwarp.neural.extraction.state import ModelInputs
from slwarp.neural.extraction.steps import side_lines, split_ramps
from slwarp.neural.pattern_model import blur_patterns, lit_with_contrast, offset_and_modulation
from slwarp.sim.simulate import SimOptions, simulate_scene

BLUR = 1.0  # projector px: the simulated defocus, and the blur the patterns are rendered with
FOOTPRINTS = 10.0
RADIUS = 10  # px on the small rig's 320 x 256 camera


@pytest.fixture(scope="module")
def boxes():
    """(scan, rendered patterns, valid pixels, the right depth map, a ramp map, the ramp's pixels) of the small-rig
    boxes scene (no noise, flat albedo); the ramp: the right map Gaussian-smoothed (3 px) within 7 px of each depth
    step, as a smooth field draws a step. Simulated on a GPU where there is one."""
    opts = SimOptions(noise=False, bits=0, defocus_sigma=BLUR, defocus_slope=0.0, shading=False, texture=False)
    scan = simulate_scene("boxes", "random6", rig="small", options=opts,
                          device="cuda:0" if torch.cuda.is_available() else "cpu")
    patterns = blur_patterns(torch.as_tensor(scan.patterns), BLUR).numpy()
    valid = lit_with_contrast(offset_and_modulation(scan.images)[1]) & np.isfinite(scan.gt_depth)
    gt = np.where(valid, scan.gt_depth, np.nan).astype(np.float32)
    known = np.isfinite(gt)
    num = cv2.GaussianBlur(np.where(known, gt, 0).astype(np.float32), (0, 0), 3)
    smooth = num / np.maximum(cv2.GaussianBlur(known.astype(np.float32), (0, 0), 3), 1e-6)
    band = (depth_step_distance(scan.gt_depth) < 7.5) & valid
    ramp = np.where(band, smooth, gt).astype(np.float32)
    return scan, patterns, valid, gt, ramp, band


def _inputs(scan, patterns, valid, device="cpu") -> ModelInputs:
    if device != "cpu":  # the extraction on a GPU: the model's arrays as tensors there
        return ModelInputs(scan.camera, scan.projector, torch.as_tensor(scan.images, device=device),
                           torch.as_tensor(patterns, device=device), scan.depth_range, valid=valid, device=device,
                           host_images=scan.images)
    return ModelInputs(scan.camera, scan.projector, scan.images, patterns, scan.depth_range, valid=valid)


def test_side_lines_fit_the_depths_on_each_side():
    H, W = 40, 60
    y, x = np.mgrid[0:H, 0:W].astype(np.float64)
    depth = torch.as_tensor(np.where(x < 30, 500.0 + 0.5 * x, 700.0 - 0.25 * x))
    depth[5, 10] = float("nan")  # a hole: fitted around
    a, b, rms, n = side_lines(depth, axis=1, side=-1, start=3, length=8)
    # at x = 20 the left side (x 9-17) is on the first plane: its line through the pixel
    assert a[10, 20].item() == pytest.approx(510.0) and b[10, 20].item() == pytest.approx(0.5)
    assert rms[10, 20].item() < 1e-9 and n[10, 20].item() == 8 and n[5, 20].item() == 7
    # at x = 35 the left side (x 24-32) crosses the step: a poor line, which the split does not use
    assert rms[10, 35].item() > 10.0
    a, b, rms, n = side_lines(depth, axis=1, side=1, start=3, length=8)
    assert a[10, 35].item() == pytest.approx(700.0 - 0.25 * 35) and b[10, 35].item() == pytest.approx(-0.25)
    assert np.isnan(a[10, W - 4].item()) and n[10, W - 4].item() == 1  # too few depths
    a, b, rms, n = side_lines(depth, axis=0, side=1, start=2, length=5)
    assert a[3, 40].item() == pytest.approx(690.0) and b[3, 40].item() == pytest.approx(0.0)


def test_a_ramp_across_the_steps_is_given_back_to_its_surfaces(boxes):
    scan, patterns, valid, gt, ramp, band = boxes
    before = np.abs(ramp - gt)[band].mean()
    assert band.sum() > 5000 and before > 10.0
    out, switched = split_ramps(ramp, _inputs(scan, patterns, valid), RADIUS, FOOTPRINTS, 0.9)
    after = np.abs(out - gt)[band].mean()
    assert after < 0.75 * before
    assert switched.sum() > 1000 and not (switched & ~band).any()
    fixed = switched & (np.abs(out - gt) < np.abs(ramp - gt))
    assert fixed.sum() > 0.9 * switched.sum()
    np.testing.assert_array_equal(out[~switched], ramp[~switched])
    assert np.array_equal(np.isfinite(out), np.isfinite(ramp))  # nothing dropped, nothing filled


def test_the_right_map_and_radius_0_change_nothing(boxes):
    scan, patterns, valid, gt, ramp, band = boxes
    inputs = _inputs(scan, patterns, valid)
    out, switched = split_ramps(gt, inputs, RADIUS, FOOTPRINTS, 0.9)
    assert switched.sum() <= 5
    same, none = split_ramps(ramp, inputs, 0, FOOTPRINTS, 0.9)
    assert not none.any()
    np.testing.assert_array_equal(same, ramp)


def test_every_device_splits_as_the_cpu_does(boxes, device):
    scan, patterns, valid, gt, ramp, band = boxes
    want, want_sw = split_ramps(ramp, _inputs(scan, patterns, valid), RADIUS, FOOTPRINTS, 0.9)
    got, got_sw = split_ramps(ramp, _inputs(scan, patterns, valid, device), RADIUS, FOOTPRINTS, 0.9)
    # the residuals' float rounding differs between devices: a pixel at the margin may go either way
    assert (got_sw != want_sw).sum() <= 0.01 * want_sw.sum()
    both = got_sw & want_sw
    np.testing.assert_allclose(got[both], want[both], atol=1e-3)


def test_the_stage_runs_in_fast_and_accurate_and_its_switch_removes_it():
    for name in ("fast", "accurate"):
        stages = preset(name).extraction.stages
        assert "step_split" in stages and stages.index("step_split") < stages.index("edge_side")
        assert "step_split" not in preset(name, step_split_radius=0).extraction.stages
    assert "step_split" not in preset("cpu-hashgrid").extraction.stages
    assert "step_split" in preset("cpu-hashgrid", step_split_radius=6).extraction.stages
