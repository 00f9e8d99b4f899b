"""Confidence maps: the sparsification metrics against hand-computed values, the classical decoders' confidence
(code certainty, signal swing), the neural terms on scans and fields whose answer is known, the files and the
`evaluate` / `decode` commands that read and write them."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from slwarp.cli import main as cli_main
from slwarp.decode import decode, decoding_confidence, reconstruct_depth
from slwarp.decode.confidence import code_certainty, signal_swing
from slwarp.evaluation.metrics import confidence_metrics, depth_metrics, sparsification_curve
from slwarp.evaluation.outputs import read_confidence, write_confidence
from slwarp.neural.extraction.confidence import combine, ray_confidence, uniqueness_confidence
from slwarp.neural.config import ConfigError, preset
from slwarp.neural.pattern_model import blur_patterns, photometric_confidence, photometric_residual
from slwarp.neural.render import StructuredLightRenderer
from slwarp.sim.simulate import SimOptions, simulate_scene

# ----------------------------------------------------------------------------------------------
# metrics


def test_sparsification_curve_hand_computed():
    err = np.array([1.0, 2.0, 3.0, 4.0])
    conf = np.array([0.9, 0.1, 0.5, 0.7])  # order: 1, 4, 3, 2
    curve = sparsification_curve(err, conf, [1.0, 0.75, 0.625, 0.5, 0.25])
    np.testing.assert_allclose(curve, [2.5, 8 / 3, (1 + 4 + 0.5 * 3) / 2.5, 2.5, 1.0])
    oracle = sparsification_curve(err, -err, [1.0, 0.5, 0.25])
    np.testing.assert_allclose(oracle, [2.5, 1.5, 1.0])
    # a tie group cut in part counts its mean error, whatever the pixel order
    for e in ([1.0, 3.0, 2.0, 2.0], [3.0, 1.0, 2.0, 2.0]):
        assert sparsification_curve(np.array(e), np.array([1.0, 1.0, 0.0, 0.0]), [0.25])[0] == pytest.approx(2.0)
    with pytest.raises(ValueError, match="fractions"):
        sparsification_curve(err, conf, [0.0])
    with pytest.raises(ValueError, match="same pixels"):
        sparsification_curve(err, conf[:3], [1.0])


def test_the_oracle_curve_is_the_curve_ranked_by_the_error():
    """confidence_metrics' oracle (a plain sort of the errors) is sparsification_curve with the errors' negatives as
    confidence, ties and partly cut pixels included."""
    from slwarp.evaluation.metrics import SPARSIFICATION_FRACTIONS, _oracle_curve

    rng = np.random.default_rng(0)
    for n in (1, 7, 1000):
        err = np.abs(rng.normal(size=n))
        err[: n // 3] = np.round(err[: n // 3], 1)  # ties
        np.testing.assert_allclose(_oracle_curve(err, SPARSIFICATION_FRACTIONS),
                                   sparsification_curve(err, -err, SPARSIFICATION_FRACTIONS), rtol=1e-12)
    assert np.isnan(_oracle_curve(np.array([]), [1.0, 0.5])).all()


def test_confidence_metrics_hand_computed():
    gt = np.full((2, 3), 500.0)
    gt[1, 2] = np.nan  # not compared
    pred = gt + np.array([[1.0, -2.0, 3.0], [4.0, 9.0, 0.0]])
    pred[1, 1] = np.nan  # no prediction: not compared either
    conf = np.array([[0.9, 0.1, 0.5], [0.7, 1.0, np.nan]])
    m = confidence_metrics(pred, conf, gt, fractions=[1.0, 0.5])
    # compared errors 1, 2, 3, 4 with confidence 0.9, 0.1, 0.5, 0.7: as in the curve test
    assert m["sparsification"]["curve"] == pytest.approx([2.5, 2.5])
    assert m["sparsification"]["oracle"] == pytest.approx([2.5, 1.5])
    assert m["ause"] == pytest.approx(0.5)  # the trapezoid of (0, 1) over a width of 0.5, divided by it
    assert m["ause_random"] == pytest.approx(0.5)
    assert m["mae_top90"] == pytest.approx((1 + 4 + 3 + 0.6 * 2) / 3.6)
    assert m["mae_top75"] == pytest.approx(8 / 3)
    # a perfect ranking has AUSE 0; non-finite confidence on a compared pixel ranks last
    perfect = confidence_metrics(pred, -np.abs(pred - gt), gt)
    assert perfect["ause"] == pytest.approx(0.0, abs=1e-12) and perfect["ause_random"] > 0
    conf_nan = np.array([[np.nan, 0.1, 0.5], [0.7, 1.0, 1.0]])  # error 1 pixel last
    assert confidence_metrics(pred, conf_nan, gt, fractions=[0.75])["sparsification"]["curve"][0] == pytest.approx(3.0)
    with pytest.raises(ValueError, match="confidence shape"):
        confidence_metrics(pred, conf[:1], gt)
    empty = confidence_metrics(np.full((2, 3), np.nan), conf, gt)
    assert np.isnan(empty["ause"]) and np.isnan(empty["mae_top90"])


def test_confidence_files_round_trip_and_bad_input(tmp_path):
    c = np.array([[0.0, 0.5], [1.0, np.nan]], np.float32)
    write_confidence(tmp_path, c)
    np.testing.assert_array_equal(read_confidence(tmp_path / "confidence.npy", (2, 2)), c)
    with pytest.raises(ValueError, match="2x2"):
        read_confidence(tmp_path / "confidence.npy", (3, 2))
    np.save(tmp_path / "big.npy", np.array([[0.5, 1.5]]))
    with pytest.raises(ValueError, match=r"\[0, 1\].*1.5"):
        read_confidence(tmp_path / "big.npy")
    np.save(tmp_path / "flat.npy", np.zeros(4))
    with pytest.raises(ValueError, match="2-D"):
        read_confidence(tmp_path / "flat.npy")
    with pytest.raises(ValueError, match=r"\.npy"):
        read_confidence(tmp_path / "confidence.png")
    with pytest.raises(FileNotFoundError, match="not found"):
        read_confidence(tmp_path / "missing.npy")


# ----------------------------------------------------------------------------------------------
# classical decoders


def test_code_certainty_skips_the_bits_of_the_stripe_boundaries():
    # 3 stripes of a 2-bit Gray code: 00, 01, 11; flips: stripe 1 flips bit 1, stripe 2 flips bit 0
    flips = np.array([[False, False], [False, True], [True, False]])
    signal = np.array([[[0.2, 0.9, -0.4, 0.05]], [[-0.3, 0.05, 0.8, -2.0]]])  # [n=2, H=1, W=4]
    stripe = np.array([[0, 1, 2, -1]])
    c = code_certainty(signal, stripe, flips)
    # stripe 0: boundary to 1 flips bit 1 -> bit 0 counts (0.2); stripe 1: both bits flip at its boundaries -> 1;
    # stripe 2: its own boundary flips bit 0, no stripe after it -> bit 1 counts (0.8); invalid -> NaN
    np.testing.assert_allclose(c[0, :3], [0.2, 1.0, 0.8])
    assert np.isnan(c[0, 3])
    np.testing.assert_allclose(signal_swing(np.array([0.1, 0.3, 0.6, -0.1])), [0.2, 0.6, 1.0, 0.0])


@pytest.fixture(scope="module")
def classical_scan():
    return simulate_scene("boxes", "gray7+npmp6", "small", SimOptions(seed=2), device="cpu")


def test_decoding_confidence_ranks_the_errors(classical_scan):
    s = classical_scan
    for method, frames in (("gc-interp", "gray:col:bit=0-6"), ("npmp", "phase:col")):
        depth, _, dec = reconstruct_depth(s, method, frames=frames)
        conf = decoding_confidence(dec, depth)
        fin = np.isfinite(depth)
        assert np.array_equal(np.isfinite(conf), fin) and conf[fin].min() >= 0 and conf[fin].max() <= 1
        m = confidence_metrics(depth, conf, s.gt_depth, s.mask)
        # measured (seed 2): gc-interp AUSE 0.16 of 0.29 for a ranking of nothing; npmp 0.31 of 0.70
        assert m["ause"] < 0.75 * m["ause_random"], (method, m["ause"], m["ause_random"])
        assert m["mae_top75"] < depth_metrics(depth, s.gt_depth, s.mask)["mae"]
    # the product of its parts: amplitude swing x code certainty for Gray code, modulation swing for phase
    dec = decode(s, "gc-interp", frames="gray:col:bit=0-6")
    ok = dec.valid
    expect = signal_swing(dec.extra["amplitude_col"]) * dec.extra["certainty_col"]
    np.testing.assert_allclose(decoding_confidence(dec)[ok], expect[ok], rtol=1e-6)
    dec = decode(s, "npmp")
    np.testing.assert_allclose(decoding_confidence(dec)[dec.valid], signal_swing(dec.extra["modulation"])[dec.valid],
                               rtol=1e-6)


# ----------------------------------------------------------------------------------------------
# neural terms


@pytest.fixture(scope="module")
def blurred_scan():
    """Small-rig scene with a depth-independent projector blur of 1 px and no noise (as test_pattern_model)."""
    opts = SimOptions(noise=False, bits=0, defocus_sigma=1.0, defocus_slope=0.0, shading=False, texture=False)
    return simulate_scene("steps", "random6", rig="small", options=opts, device="cpu")


def test_photometric_confidence_is_one_minus_the_residual(blurred_scan):
    s = blurred_scan
    pats = blur_patterns(torch.as_tensor(s.patterns), 1.0).numpy()
    depth = np.where(s.mask, s.gt_depth, np.nan)
    depth[::7] += 150.0  # wrong rows: their codes do not match
    c = photometric_confidence(depth, s.camera, s.projector, s.images, pats)
    r = photometric_residual(depth, s.camera, s.projector, s.images, pats)
    fin = np.isfinite(depth)
    np.testing.assert_allclose(c[fin], np.clip(1 - r[fin], 0, 1), atol=1e-6)
    assert np.array_equal(np.isfinite(c), fin)
    # the photometric check of old (drop r >= 0.4) is min_confidence 0.6 on this term
    assert np.array_equal((c >= 0.6)[fin], (r < 0.4)[fin] | np.isclose(r[fin], 0.4))


def test_uniqueness_separates_right_from_wrong_depths(blurred_scan):
    s = blurred_scan
    pats = blur_patterns(torch.as_tensor(s.patterns), 1.0).numpy()
    ok = s.mask & np.isfinite(s.gt_depth)
    right = uniqueness_confidence(np.where(ok, s.gt_depth, np.nan), s.camera, s.projector, s.images, pats,
                                  (450.0, 1100.0))
    wrong = uniqueness_confidence(np.where(ok, s.gt_depth + 40.0, np.nan), s.camera, s.projector, s.images, pats,
                                  (450.0, 1100.0))
    assert np.array_equal(np.isfinite(right), ok)
    # at the true depth the codes fit far better than anywhere else on the ray; 40 mm off, the true depth is a
    # rival that fits better (measured: medians 0.97 and 0.0)
    assert np.median(right[ok]) > 0.8 and np.median(wrong[ok]) < 0.1


class PlaneSDF(torch.nn.Module):
    """f(x) = z0 - ... : a fronto-parallel plane at camera z = z0 (mm), solid behind it."""

    def __init__(self, z0: float):
        super().__init__()
        self.z0 = z0
        self.dummy = torch.nn.Parameter(torch.zeros(()))

    def forward(self, x):
        return self.z0 - x[..., 2] + 0.0 * self.dummy


def test_ray_confidence_of_a_plane(blurred_scan):
    s = blurred_scan
    renderer = StructuredLightRenderer.from_scan(s, PlaneSDF(700.0), n_samples=32, n_importance=16, up_sample_steps=2,
                                                 backend="torch")
    with torch.no_grad():
        renderer.variance.v.fill_(0.8)  # inv_s = exp(8) / scale: a sharp surface (scale: a few hundred mm)
    H, W = s.camera.height, s.camera.width
    depth = np.full((H, W), 700.0, np.float32)
    depth[:, : W // 2] = 760.0  # left half: 60 mm behind the plane the weights sit on
    depth[0, 0] = np.nan
    peak, agree = ray_confidence(renderer, depth, rays_per_chunk=5000)
    assert np.isnan(peak[0, 0]) and np.isnan(agree[0, 0])
    right, left = np.s_[:, W // 2 :], np.s_[1:, : W // 2]
    # measured 0.9999 and 0.87: with this sharpness the rendered depth of a plane sits 0.14 mm in front of it
    assert peak[right].min() > 0.95 and agree[right].min() > 0.8
    assert peak[left].max() < 0.05 and agree[left].max() < 1e-6  # exp(-60)


def test_combine_is_the_geometric_mean():
    t = {"a": np.array([[1.0, 0.25, np.nan]]), "b": np.array([[0.25, 0.0, 1.0]])}
    np.testing.assert_allclose(combine(t, ("a", "b")), [[0.5, 0.0, np.nan]])


def test_min_confidence_option():
    cfg = preset("tiny", min_confidence=0.3, confidence="peak")
    assert cfg.extraction.min_confidence == 0.3 and cfg.extraction.confidence == "peak"
    assert preset("tiny").extraction.confidence == "photometric" and preset("tiny").extraction.min_confidence == 0.6
    with pytest.raises(ConfigError, match="min_confidence"):
        preset("tiny", min_confidence=1.5)
    with pytest.raises(ConfigError, match="confidence"):
        preset("tiny", confidence="vibes")


# ----------------------------------------------------------------------------------------------
# commands


@pytest.fixture(scope="module")
def scan_dir(tmp_path_factory, classical_scan):
    folder = tmp_path_factory.mktemp("scan")
    classical_scan.save(folder)
    return folder


def test_cli_decode_writes_confidence_and_evaluate_reads_it(scan_dir, tmp_path, capsys):
    out = tmp_path / "gc"
    assert cli_main(["decode", str(scan_dir), "--method", "gc-interp", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "AUSE mm" in printed and "confidence.npy" in printed
    conf = np.load(out / "confidence.npy")
    depth = np.load(out / "depth.npy")
    assert conf.dtype == np.float32 and np.array_equal(np.isfinite(conf), np.isfinite(depth))
    assert (out / "confidence.png").is_file()
    doc = json.loads((out / "metrics.json").read_text())
    assert doc["confidence"]["ause"] < doc["confidence"]["ause_random"]
    # evaluate finds confidence.npy beside the prediction and reports the same numbers
    assert cli_main(["evaluate", str(out / "depth.npy"), str(scan_dir), "--out", str(tmp_path / "ev")]) == 0
    printed = capsys.readouterr().out
    assert "MAE top 90% mm" in printed
    ev = json.loads((tmp_path / "ev" / "evaluation.json").read_text())
    assert ev["confidence"]["ause"] == pytest.approx(doc["confidence"]["ause"])
    assert ev["confidence_map"] == str(out / "confidence.npy")
    # --confidence FILE: a ranking by the true error gives AUSE 0
    from slwarp.scans.scan import load_scan

    gt = load_scan(scan_dir).gt_depth
    np.save(tmp_path / "oracle.npy", (1.0 / (1.0 + np.abs(depth - gt))).astype(np.float32))
    assert cli_main(["evaluate", str(out / "depth.npy"), str(scan_dir), "--out", str(tmp_path / "ev2"),
                     "--confidence", str(tmp_path / "oracle.npy")]) == 0
    capsys.readouterr()
    assert json.loads((tmp_path / "ev2" / "evaluation.json").read_text())["confidence"]["ause"] == pytest.approx(0, abs=1e-9)
    # a bad confidence file is a one-line error naming it
    np.save(tmp_path / "bad.npy", np.full((3, 3), 0.5))
    assert cli_main(["evaluate", str(out / "depth.npy"), str(scan_dir), "--confidence", str(tmp_path / "bad.npy")]) == 2
    err = capsys.readouterr().err
    assert "bad.npy" in err and "confidence map is 3x3" in err and len(err.strip().splitlines()) == 1
