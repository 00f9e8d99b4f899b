"""Pattern sets: Gray code against g = b ^ (b >> 1), uniform random squares, phase shift, named sets."""
import numpy as np
import pytest

from slwarp import patterns as P


@pytest.mark.parametrize("size,bits", [(1280, 7), (1280, 6), (1024, 10), (800, 5), (1000, 9)])
@pytest.mark.parametrize("axis", ["col", "row"])
def test_gray_code_formula(size, bits, axis):
    w, h = (size, 37) if axis == "col" else (41, size)
    ps = P.gray_code(w, h, bits, axis=axis, inverse=True)
    assert len(ps) == 2 * bits and ps.patterns.dtype == np.float32
    coord = np.arange(size)
    # decode the bits back, MSB first
    prof = ps.patterns[:, 0, :] if axis == "col" else ps.patterns[:, :, 0]
    g = np.zeros(size, np.int64)
    for k in range(bits):
        assert ps.names[2 * k] == f"gc_{axis}_b{k}" and ps.names[2 * k + 1] == f"gc_{axis}_b{k}_inv"
        assert np.array_equal(prof[2 * k + 1], 1 - prof[2 * k])
        g = (g << 1) | prof[2 * k].astype(np.int64)
    stripe = coord * (1 << bits) // size
    assert np.array_equal(g, stripe ^ (stripe >> 1))
    assert np.array_equal(P.gray_to_binary(g), stripe)
    # constant along the other axis
    assert np.all(ps.patterns == (ps.patterns[:, :1, :] if axis == "col" else ps.patterns[:, :, :1]))


def test_gray_prefix_is_shorter_code():
    full = P.gray_code(1280, 8, 7)
    short = P.gray_code(1280, 8, 5)
    assert np.array_equal(full.patterns[:5], short.patterns)


@pytest.mark.parametrize("per_scale", [1, 2, 3])
def test_random_squares_uniform(per_scale):
    w, h = 1280, 800
    ps = P.random_binary(w, h, per_scale=per_scale, seed=3)
    assert len(ps) == 3 * per_scale
    assert ps.names[:3] == ["rand20_0", "rand10_0", "rand5_0"]
    for img, name in zip(ps.patterns, ps.names):
        s = int(name[4:].split("_")[0])
        assert set(np.unique(img)) <= {0.0, 1.0}
        for y0 in range(0, h, s):
            for x0 in range(0, w, s * 7):  # a sample of squares along each row of squares
                sq = img[y0 : y0 + s, x0 : x0 + s]
                assert sq.min() == sq.max(), f"{name}: square at ({x0},{y0}) not uniform"
        frac = img.mean()
        assert 0.45 < frac < 0.55
    # seeded and repeatable; different seeds differ
    again = P.random_binary(w, h, per_scale=per_scale, seed=3)
    assert np.array_equal(again.patterns, ps.patterns)
    assert not np.array_equal(P.random_binary(w, h, per_scale=per_scale, seed=4).patterns, ps.patterns)


def test_phase_shift_values_and_decoding():
    ps = P.phase_shift(640, 4, 40.0, 4)
    assert ps.names == [f"ps_col_p40_s{k}of4" for k in range(4)]
    u = np.arange(640)
    I = ps.patterns[:, 0, :].astype(np.float64)
    delta = 2 * np.pi * np.arange(4) / 4
    phi = np.arctan2((I * np.sin(delta)[:, None]).sum(0), (I * np.cos(delta)[:, None]).sum(0))
    diff = np.angle(np.exp(1j * (phi - 2 * np.pi * u / 40.0)))
    assert np.abs(diff).max() < 1e-5
    assert ps.patterns.min() >= 0 and ps.patterns.max() <= 1


@pytest.mark.parametrize(
    "name,count",
    [("random6", 6), ("random9", 9), ("gray6", 6), ("gray7", 7), ("gray7inv", 14), ("gt", 18),
     ("cgc6", 6), ("cgc7", 7), ("hpmp6", 6), ("npmp6", 6), ("ps4", 4), ("whiteblack", 2), ("grayrow5inv", 10)],
)
def test_named_sets(name, count):
    ps = P.named_set(name, 1280, 800)
    assert len(ps) == count
    assert ps.patterns.shape == (count, 800, 1280)
    assert ps.patterns.dtype == np.float32 and ps.patterns.min() >= 0 and ps.patterns.max() <= 1


def test_named_set_details():
    cgc6 = P.named_set("cgc6", 1280, 800)
    assert cgc6.names[:3] == ["gc_col_b0", "gc_col_b1", "gc_col_b2"]
    assert cgc6.names[3].startswith("ps_col_p320_")
    assert P.named_set("cgc7", 1280, 800).names[4].startswith("ps_col_p160_")
    assert [n.split("_s")[0] for n in P.named_set("npmp6", 1280, 800).names] == ["ps_col_p48"] * 3 + ["ps_col_p70"] * 3
    gt = P.named_set("gt", 1280, 800)
    assert gt.names[:2] == ["gc_col_b0", "gc_col_b0_inv"] and gt.names[-1] == "ps_col_p40_s3of4"
    combo = P.named_set("random6+gray7+gt", 1280, 800)
    assert len(combo) == 6 + 7 + 7 + 4  # gt's Gray code bits shared with gray7 are kept once


def test_unknown_and_bad_named_sets():
    with pytest.raises(ValueError, match="unknown pattern set"):
        P.named_set("zebra", 100, 100)
    with pytest.raises(ValueError, match="multiple of 3"):
        P.named_set("random7", 100, 100)
    with pytest.raises(ValueError, match="co-prime"):
        P.number_theoretic_pmp(1280, 800, (40, 80))
    with pytest.raises(ValueError, match="unambiguous"):
        P.number_theoretic_pmp(1280, 800, (20, 30))


def test_procam_patterns_are_opencv_gray_code(chessboard_path):
    from slwarp.scans.scan import load_scan

    scan = load_scan(chessboard_path)
    ours = P.gray_code(1024, 768, 10, "col", inverse=True)
    for name, pat in zip(ours.names, ours.patterns):
        assert np.array_equal(scan.patterns[scan.names.index(name)], pat), name
    assert scan.patterns[scan.names.index("white")].min() == 1.0
    assert scan.patterns[scan.names.index("black")].max() == 0.0
