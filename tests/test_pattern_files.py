"""Designed pattern sets as first-class pattern sets: the `designed` role and its names, pattern-set files (write, read,
errors naming the file), named_set with a path, `slwarp simulate --patterns FILE`, `Scan.with_patterns` and
`slwarp reconstruct --patterns FILE` (one scan and a batch)."""
from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from slwarp.cli import main as cli_main
from slwarp.scans.pattern_files import (PATTERN_SET_FILE, is_pattern_set_path, read_pattern_set, read_pattern_set_meta,
                                        write_pattern_set)
from slwarp.scans.patterns import PatternSet, designed_names, named_set, random_binary
from slwarp.scans.roles import (FrameRole, RoleError, parse_role, parse_selector, resolve_roles, role_from_name,
                                role_groups)
from slwarp.scans.scan import ScanError, load_scan
from slwarp.sim.rigs import make_rig

SMALL_PROJECTOR = make_rig("small")[1]


def designed(k: int = 4, width: int = 48, height: int = 32, seed: int = 0) -> PatternSet:
    """K grey-level patterns whose values per projector pixel span 0..1 (as a design's do)."""
    rng = np.random.default_rng(seed)
    pats = rng.random((k, height, width))
    pats = (pats - pats.min(0)) / (pats.max(0) - pats.min(0))
    return PatternSet(pats.astype(np.float32), designed_names(k))


def quantised(pats: np.ndarray) -> np.ndarray:
    return (np.rint(pats.astype(np.float64) * 255) / 255).astype(np.float32)


@pytest.fixture(scope="module")
def small_set(tmp_path_factory):
    """(PatternSet, its patterns.yaml) at the small rig's projector size."""
    pset = designed(4, SMALL_PROJECTOR.width, SMALL_PROJECTOR.height, seed=1)
    return pset, write_pattern_set(tmp_path_factory.mktemp("design") / "set", pset, {"rig": "small"})


@pytest.fixture(scope="module")
def designed_scan(small_set, tmp_path_factory):
    """A small-rig scan simulated with the designed set + white/black, written by `slwarp simulate --patterns`."""
    _, f = small_set
    out = tmp_path_factory.mktemp("scan") / "s"
    assert cli_main(["simulate", "--scene", "bunny", "--rig", "small", "--patterns", f"{f}+whiteblack",
                     "--device", "cpu", "--out", str(out)]) == 0
    return out


# ----------------------------------------------------------------------------------------------
# the role


def test_designed_role_and_its_name():
    role = FrameRole("designed", index=2, count=4)
    assert role.name == "design4_2" and role_from_name("design4_2") == role
    assert parse_role({"kind": "designed", "index": 2, "count": 4}) == role == parse_role("designed:count=4:index=2")
    assert parse_role(role.to_yaml()) == role and role.to_yaml() == {"kind": "designed", "index": 2, "count": 4}
    assert parse_role(role.label()) == role
    assert designed_names(3) == ["design3_0", "design3_1", "design3_2"]
    assert role_from_name("design4_4") is None and role_from_name("design0_0") is None  # not valid roles
    with pytest.raises(ValueError, match="at least 1 pattern"):
        designed_names(0)
    for bad, message in [({"kind": "designed", "index": 0}, "a designed role needs count"),
                         ({"kind": "designed", "index": 4, "count": 4}, r"index must be in 0..count-1 \(3\)"),
                         ({"kind": "designed", "index": 0, "count": 4, "size": 3}, "'size' is not a field")]:
        with pytest.raises(RoleError, match=message):
            resolve_roles(["f"], {"f": bad})
    with pytest.raises(RoleError, match="contradicts its name"):
        resolve_roles(["design4_1"], {"design4_1": {"kind": "designed", "index": 2, "count": 4}})


def test_designed_selectors_and_groups():
    names = designed_names(4) + designed_names(2) + ["rand20_0", "white"]
    roles = resolve_roles(names)

    def pick(token):
        sel = parse_selector(token)
        return [n for n, r in zip(names, roles) if sel.matches(r)]

    assert pick("designed:count=4") == designed_names(4) and len(pick("designed")) == 6
    assert pick("designed:index=0-2") == designed_names(4)[:3] + designed_names(2)
    assert pick("random") == ["rand20_0"]
    with pytest.raises(RoleError, match="designed frames have no axis"):
        parse_selector("designed:col")
    labels = [label for label, _ in role_groups(names, roles)]
    assert labels[:2] == ["designed:count=4 (index=0-3)", "designed:count=2 (index=0-1)"]


# ----------------------------------------------------------------------------------------------
# pattern-set files


def test_write_read_round_trip(tmp_path):
    pset = designed(4)
    f = write_pattern_set(tmp_path / "set", pset, {"rig": "small", "depth_range": [400.0, 1100.0]})
    assert f == tmp_path / "set" / PATTERN_SET_FILE
    written = sorted(p.name for p in (tmp_path / "set").iterdir())
    assert written == sorted([PATTERN_SET_FILE] + [f"{n}.png" for n in pset.names])
    doc = yaml.safe_load(f.read_text())
    assert doc["format"] == "slwarp-pattern-set" and doc["version"] == 1 and (doc["width"], doc["height"]) == (48, 32)
    assert doc["frames"][1] == {"name": "design4_1", "pattern": "design4_1.png",
                                "role": {"kind": "designed", "index": 1, "count": 4}}
    for where in (f, tmp_path / "set", str(tmp_path / "set")):
        back = read_pattern_set(where)
        assert back.names == pset.names and back.source == str(f)
        assert np.array_equal(back.patterns, quantised(pset.patterns))  # 8-bit: k / 255, exactly
        assert [r.kind for r in back.frame_roles()] == ["designed"] * 4
    assert read_pattern_set_meta(f) == {"rig": "small", "depth_range": [400.0, 1100.0]}
    # a quantised set writes and reads back unchanged
    again = write_pattern_set(tmp_path / "again", back)
    assert np.array_equal(read_pattern_set(again).patterns, back.patterns)
    assert is_pattern_set_path(str(f)) and is_pattern_set_path(str(tmp_path / "set")) and is_pattern_set_path("x.yml")
    assert not is_pattern_set_path("random6") and not is_pattern_set_path(str(tmp_path))


def test_roles_of_other_names_travel_with_the_set(tmp_path):
    pset = PatternSet(np.stack([np.ones((4, 6)), np.zeros((4, 6))]), ["on", "off"],
                      roles={"on": "white", "off": {"kind": "black"}})
    back = read_pattern_set(write_pattern_set(tmp_path / "s", pset))
    assert back.frame_roles() == [FrameRole("white"), FrameRole("black")]
    # numpy values in meta are written as plain numbers; what yaml cannot hold is refused, naming the entry
    f = write_pattern_set(tmp_path / "m", pset, {"range": np.array([400.0, 1100.0]), "loss": np.float32(0.5),
                                                 "size": (640, 400)})
    assert read_pattern_set_meta(f) == {"range": [400.0, 1100.0], "loss": 0.5, "size": [640, 400]}
    with pytest.raises(ValueError, match=r"meta.opts: a object cannot be written"):
        write_pattern_set(tmp_path / "bad", pset, {"opts": object()})
    with pytest.raises(ValueError, match="values must be finite and in"):
        write_pattern_set(tmp_path / "bad", PatternSet(np.full((1, 4, 6), 1.5), ["x"]))
    with pytest.raises(ValueError, match="not plain file names"):
        write_pattern_set(tmp_path / "bad", PatternSet(np.zeros((1, 4, 6)), ["../x"]))


def _edit(f, change):
    doc = yaml.safe_load(f.read_text())
    change(doc)
    f.write_text(yaml.safe_dump(doc, sort_keys=False))


@pytest.mark.parametrize("case,message", [
    ("missing png", "pattern of frame 'design4_2' of {f} not found: {folder}/design4_2.png"),
    ("wrong size", "{folder}/design4_0.png: pattern of frame 'design4_0' is 24x32, {f} says 48x32"),
    ("format", "{f}: not a pattern set: format is 'slwarp-scan', expected 'slwarp-pattern-set'"),
    ("version", "{f}: pattern-set version 2 is not one this slwarp reads (1)"),
    ("duplicate", "{f}: frame name 'design4_0' appears twice (frames 0 and 1)"),
    ("role", "{f}: frame 'design4_1': its role designed:count=4:index=3 contradicts its name"),
    ("not png", "pattern of frame 'design4_3' of {f} is unreadable or corrupt"),
    ("outside", "{f}: frames[0].pattern '../elsewhere.png' leads outside"),
    ("yaml", "{f}: not valid YAML"),
])
def test_read_errors_name_the_file(tmp_path, case, message):
    f = write_pattern_set(tmp_path / "set", designed(4))
    folder = f.parent
    if case == "missing png":
        (folder / "design4_2.png").unlink()
    elif case == "wrong size":
        write_pattern_set(tmp_path / "other", designed(2, width=24))
        (tmp_path / "other" / "design2_0.png").replace(folder / "design4_0.png")
    elif case == "format":
        _edit(f, lambda d: d.update(format="slwarp-scan"))
    elif case == "version":
        _edit(f, lambda d: d.update(version=2))
    elif case == "duplicate":
        _edit(f, lambda d: d["frames"][1].update(name="design4_0"))
    elif case == "role":
        _edit(f, lambda d: d["frames"][1]["role"].update(index=3))
    elif case == "not png":
        (folder / "design4_3.png").write_bytes(b"not an image")
    elif case == "outside":
        _edit(f, lambda d: d["frames"][0].update(pattern="../elsewhere.png"))
    elif case == "yaml":
        f.write_text("frames: [unclosed\n")
    with pytest.raises(ScanError) as e:
        read_pattern_set(folder)
    assert message.format(f=f, folder=folder) in str(e.value)


def test_missing_set_and_folder_without_one(tmp_path):
    with pytest.raises(ScanError, match=f"pattern set not found: {tmp_path}/nope.yaml"):
        read_pattern_set(tmp_path / "nope.yaml")
    with pytest.raises(ScanError, match=f"{tmp_path}: no patterns.yaml in this folder"):
        read_pattern_set(tmp_path)


# ----------------------------------------------------------------------------------------------
# named_set and `slwarp simulate`


def test_named_set_reads_files(tmp_path):
    pset = designed(4)
    f = write_pattern_set(tmp_path / "set", pset)
    for spec in (str(f), str(f.parent)):
        assert named_set(spec, 48, 32).names == pset.names
    joined = named_set(f"random6+{f.parent}", 48, 32, seed=3)
    assert joined.names == random_binary(48, 32, per_scale=2).names + pset.names
    assert np.array_equal(joined.patterns[6:], quantised(pset.patterns))
    with pytest.raises(ValueError, match=rf"{f}: the pattern set is 48x32, the projector 64x32"):
        named_set(f"whiteblack+{f}", 64, 32)
    with pytest.raises(ValueError, match="no pattern-set file there"):
        named_set(f"random6+{tmp_path}/missing", 48, 32)
    with pytest.raises(ScanError, match="pattern set not found"):
        named_set(str(tmp_path / "typo.yaml"), 48, 32)


def test_simulate_with_a_pattern_set_file(small_set, designed_scan, capsys):
    pset, f = small_set
    scan = load_scan(designed_scan)
    assert scan.names == pset.names + ["white", "black"]
    assert np.array_equal(scan.patterns[:4], quantised(pset.patterns))  # the 16-bit copy of k / 255 is exact
    assert scan.roles[0] == FrameRole("designed", index=0, count=4)
    doc = yaml.safe_load((designed_scan / "scan.yaml").read_text())
    assert doc["frames"][3]["role"] == {"kind": "designed", "index": 3, "count": 4}
    assert scan.frame_indices("designed:count=4") == [0, 1, 2, 3]
    assert cli_main(["info", str(designed_scan), "--roles"]) == 0
    out = capsys.readouterr().out
    assert "designed:count=4 (index=0-3)" in out and "design4_2  designed:count=4:index=2" in out


def test_simulate_refuses_bad_files_in_one_line(tmp_path, small_set, capsys):
    f = write_pattern_set(tmp_path / "set", designed(2))  # 48x32: not the small projector's size
    args = ["simulate", "--scene", "bunny", "--rig", "small", "--out", str(tmp_path / "x"), "--patterns"]
    assert cli_main(args + [str(f)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (f"slwarp simulate: error: --patterns: {f}: the pattern set is 48x32, the projector "
                   f"{SMALL_PROJECTOR.width}x{SMALL_PROJECTOR.height}")
    _edit(f, lambda d: d.update(format="other"))
    assert cli_main(args + [str(f)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{f}: not a pattern set: format is 'other'" in err
    assert not (tmp_path / "x").exists()


# ----------------------------------------------------------------------------------------------
# Scan.with_patterns and `slwarp reconstruct --patterns`


def test_with_patterns(small_set, designed_scan):
    pset, f = small_set
    scan = load_scan(designed_scan)
    blank = scan.with_patterns(PatternSet(np.zeros((1, *scan.patterns.shape[1:])), ["design4_1"]))
    assert not blank.patterns[1].any() and np.array_equal(blank.patterns[0], scan.patterns[0])
    again = blank.with_patterns(read_pattern_set(f))
    assert np.array_equal(again.patterns, scan.patterns) and again.meta["pattern_set"] == str(f)
    # the set's roles replace the scan's: a frame of another name takes the role the set declares
    renamed = PatternSet(scan.patterns[4:5], ["white"], roles={"white": "white"})
    assert scan.with_patterns(renamed).roles == scan.roles
    with pytest.raises(ScanError, match=rf"{f}: frames design6_4, design6_5 of the pattern set are not in "
                                        rf"{designed_scan} \(its frames: design4_0"):
        bigger = designed(6, SMALL_PROJECTOR.width, SMALL_PROJECTOR.height)
        bigger.source = str(f)
        scan.with_patterns(bigger.subset(["design6_4", "design6_5"]))
    with pytest.raises(ScanError, match=rf"the pattern set is 48x32, the projector of {designed_scan} is "
                                        rf"{SMALL_PROJECTOR.width}x{SMALL_PROJECTOR.height}"):
        scan.with_patterns(designed(4))
    # load_scan applies the set before --frames selects, so a selection may use the set's roles
    sel = load_scan(designed_scan, frames="designed:index=0-1", patterns=f)
    assert sel.names == ["design4_0", "design4_1"]


@pytest.fixture
def stub_reconstruct(monkeypatch):
    """slwarp.neural.reconstruct.reconstruct replaced by a stub that keeps the scans it is given and stops."""
    from slwarp.neural import reconstruct as reconstruct_module

    seen = []

    def stop(scan, *args, **kwargs):
        seen.append(scan)
        raise KeyboardInterrupt

    monkeypatch.setattr(reconstruct_module, "reconstruct", stop)
    return seen


def test_reconstruct_takes_the_sets_patterns(tmp_path, small_set, designed_scan, stub_reconstruct, capsys):
    pset, f = small_set
    scan = load_scan(designed_scan)
    # the scan as it came from the projector's PC: its patterns folder holds placeholders
    stale = scan.with_patterns(PatternSet(np.zeros((4, *scan.patterns.shape[1:])), pset.names))
    stale.source = None
    stale.save(tmp_path / "stale")
    base = ["reconstruct", "--out", str(tmp_path / "o"), "--device", "cpu", "--preset", "tiny", "--quiet"]
    assert cli_main(base + [str(tmp_path / "stale"), "--patterns", str(f.parent)]) == 130
    assert np.array_equal(stub_reconstruct[-1].patterns, scan.patterns)
    assert stub_reconstruct[-1].roles == scan.roles
    # a set with a frame the scan lacks, or of another size: one line naming the file
    other = write_pattern_set(tmp_path / "six", designed(6, SMALL_PROJECTOR.width, SMALL_PROJECTOR.height))
    capsys.readouterr()
    assert cli_main(base + [str(tmp_path / "stale"), "--patterns", str(other)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert f"{other}: frames {', '.join(designed_names(6))} of the pattern set are not in {tmp_path}/stale" in err
    small = write_pattern_set(tmp_path / "small", designed(4))
    assert cli_main(base + [str(tmp_path / "stale"), "--patterns", str(small)]) == 2
    assert "the pattern set is 48x32, the projector of" in capsys.readouterr().err
    assert cli_main(base + [str(tmp_path / "stale"), "--patterns", str(tmp_path / "none.yaml")]) == 2
    assert f"pattern set not found: {tmp_path}/none.yaml" in capsys.readouterr().err


def test_reconstruct_batch_takes_the_sets_patterns(tmp_path, small_set, designed_scan, stub_reconstruct, monkeypatch):
    pset, f = small_set
    scan = load_scan(designed_scan)
    for name in ("a", "b"):
        stale = scan.with_patterns(PatternSet(np.zeros((4, *scan.patterns.shape[1:])), pset.names))
        stale.source = None
        stale.save(tmp_path / "scans" / name)
    # the stub's KeyboardInterrupt would stop the batch: make it an ordinary failure of each scan
    from slwarp.neural import reconstruct as reconstruct_module

    stop = reconstruct_module.reconstruct

    def fail(scan, *args, **kwargs):
        try:
            stop(scan)
        except KeyboardInterrupt:
            raise RuntimeError("stub") from None

    monkeypatch.setattr(reconstruct_module, "reconstruct", fail)
    assert cli_main(["reconstruct", str(tmp_path / "scans"), "--out", str(tmp_path / "o"), "--device", "cpu",
                     "--preset", "tiny", "--quiet", "--patterns", str(f)]) == 1
    assert len(stub_reconstruct) == 2
    for s in stub_reconstruct:
        assert np.array_equal(s.patterns, scan.patterns)
    rows = json.loads((tmp_path / "o" / "summary.json").read_text())["scans"]
    assert [r["error"] for r in rows] == ["RuntimeError: stub"] * 2


# the 'tiny' preset cut to a few iterations on the torch twin (as tests/test_batch.py runs it): the numbers do not
# matter here, only that a run with --patterns goes through to its outputs
FAST = ["--preset", "tiny", "--device", "cpu", "--iters", "5", "--init", "sphere", "--rays", "128",
        "--mc-resolution", "32", "--backend", "torch", "--depth-method", "sphere", "--quiet"]


def test_reconstruct_end_to_end_with_patterns(tmp_path, small_set, designed_scan, capsys):
    _, f = small_set
    assert cli_main(["reconstruct", str(designed_scan), "--out", str(tmp_path / "o"), "--patterns", str(f),
                     "--frames", "designed", *FAST]) == 0
    assert "(4 frames: design4_0, design4_1, design4_2, design4_3)" in capsys.readouterr().out
    assert np.load(tmp_path / "o" / "depth.npy").shape == (256, 320)


def test_watch_takes_the_option(tmp_path, small_set):
    from slwarp.cli import build_parser

    _, f = small_set
    argv = ["watch", str(tmp_path), "--out", str(tmp_path / "o"), "--patterns", str(f)]
    args = build_parser(argv).parse_args(argv)
    assert args.patterns == str(f)
