"""Frame roles: declared in scan.yaml or read from slwarp's names, resolved once in the Scan, read by every
decoder; selection by role; errors that name the frame; the NeSS importer's tag grammar and frame order."""
import math
import random

import cv2
import numpy as np
import pytest
import yaml

from slwarp.cli import main as cli_main
from slwarp.decode import MissingFrames, decode, reconstruct_depth
from slwarp.evaluation.metrics import depth_metrics
from slwarp.scans.patterns import PatternSet, gray_code, random_binary
from slwarp.scans.roles import FrameRole, RoleError, parse_role, parse_selector, resolve_roles, role_from_name
from slwarp.scans.scan import ScanError, load_scan, write_depth_png
from slwarp.scans.scanner import Camera, Projector
from slwarp.sim.rigs import make_rig
from slwarp.sim.scenes import build_scene
from slwarp.sim.simulate import SimOptions, simulate, simulate_scene


# ----------------------------------------------------------------------------------------------
# the role model


def test_declared_role_forms_and_names_agree():
    gray0 = FrameRole("gray", axis="col", bit=0)
    assert parse_role({"kind": "gray", "axis": "col", "bit": 0, "inverse": False}) == gray0
    assert parse_role("gray:col:bit=0") == gray0 == role_from_name("gc_col_b0")
    assert parse_role("white") == FrameRole("white") == role_from_name("white")
    phase = parse_role({"kind": "phase", "axis": "row", "period": 40, "step": 1, "steps": 4})
    assert phase == role_from_name("ps_row_p40_s1of4") and phase.name == "ps_row_p40_s1of4"
    assert parse_role("random") == FrameRole("random") and parse_role({"kind": "random", "size": 20}).size == 20.0
    # every role writes itself to yaml and reads back the same
    for r in (gray0, phase, FrameRole("black"), FrameRole("uniform", level=0.4), FrameRole("random", size=5.0, index=1, inverse=True)):
        assert parse_role(r.to_yaml()) == r and parse_role(r.label()) == r
    assert role_from_name("ps_col_p40_s5of4") is None and role_from_name("gray_b0") is None
    # a designed set made for spaced search windows: the step is part of its role and agrees with the name
    spaced = parse_role({"kind": "designed", "index": 1, "count": 3, "window_step": 3})
    assert spaced.window_step == 3 and parse_role(spaced.to_yaml()) == spaced == parse_role(spaced.label())
    assert resolve_roles(["design3_1"], {"design3_1": spaced.to_yaml()}) == [spaced]
    assert parse_selector("designed:count=3").matches(spaced) and not parse_selector("designed:window_step=2").matches(spaced)


@pytest.mark.parametrize("role,message", [
    ({"kind": "gray", "axis": "col"}, "a gray role needs bit"),
    ({"kind": "phase", "axis": "col", "period": 40, "steps": 4}, "a phase role needs step"),
    ({"kind": "phase", "axis": "col", "period": 40, "step": 4, "steps": 4}, "step must be in 0..steps-1"),
    ({"kind": "phase", "axis": "col", "period": -1, "step": 0, "steps": 3}, "period must be a positive number"),
    ({"kind": "gray", "axis": "diag", "bit": 0}, "axis must be 'col' or 'row'"),
    ({"kind": "gray", "axis": "col", "bit": 1.5}, "bit must be an integer"),
    ({"kind": "gray", "axis": "col", "bit": 0, "inverse": "yes"}, "inverse must be true or false"),
    ({"kind": "grey", "axis": "col", "bit": 0}, "unknown role kind 'grey'"),
    ({"kind": "phase", "axis": "col", "perod": 40, "step": 0, "steps": 3}, "'perod' is not a field of a phase role"),
    ({"axis": "col", "bit": 0}, "has no 'kind'"),
    ("zebra", "unknown role 'zebra'"),
    ({"kind": "uniform", "level": 2}, "level must be in [0, 1]"),
    ({"kind": "designed", "index": 0, "count": 3, "window_step": 0}, "window_step must be >= 1"),
    ({"kind": "gray", "axis": "col", "bit": 0, "window_step": 2}, "'window_step' is not a field of a gray role"),
])
def test_malformed_role_names_the_frame_and_the_problem(role, message):
    with pytest.raises(RoleError) as e:
        resolve_roles(["f0", "f1"], {"f1": role})
    assert str(e.value).startswith("frame 'f1': ") and message in str(e.value)


def test_contradictory_roles():
    with pytest.raises(RoleError, match="frames 'a' and 'b' both have the role gray:col:bit=0"):
        resolve_roles(["a", "b"], {"a": "gray:col:bit=0", "b": {"kind": "gray", "axis": "col", "bit": 0}})
    with pytest.raises(RoleError, match="frames 'white' and 'w2' both have the role white"):
        resolve_roles(["white", "w2"], {"w2": "white"})  # one by name, one declared
    with pytest.raises(RoleError, match=r"frame 'gc_col_b1': its role gray:col:bit=2 contradicts its name"):
        resolve_roles(["gc_col_b1"], {"gc_col_b1": "gray:col:bit=2"})
    # random patterns without an index may repeat; a role that agrees with the name is fine
    roles = resolve_roles(["r1", "r2", "rand20_0"], {"r1": "random", "r2": "random", "rand20_0": "random:size=20"})
    assert roles[0] == roles[1] == FrameRole("random") and roles[2] == FrameRole("random", size=20.0)


def test_selectors():
    names = gray_code(64, 8, 4, inverse=True).names + ["white", "black", "ps_col_p40_s0of3", "other"]
    roles = resolve_roles(names)

    def pick(token):
        sel = parse_selector(token)
        return [n for n, r in zip(names, roles) if sel.matches(r)]

    assert pick("gray:col:bit=0-1:noinv") == ["gc_col_b0", "gc_col_b1"]
    assert pick("gray:inv:bit=3") == ["gc_col_b3_inv"]
    assert len(pick("gray")) == 8 and pick("gray:row") == []
    assert pick("phase:period=30-50") == ["ps_col_p40_s0of3"] and pick("white") == ["white"]
    assert parse_selector("gc_col_b*") is None and parse_selector("other") is None  # names and globs
    for bad, message in [("gray:bitt=1", "unknown field 'bitt'"), ("gray:diag", "cannot read 'diag'"),
                         ("white:col", "white frames have no axis"), ("gray:bit=x", "needs a number or a range")]:
        with pytest.raises(RoleError, match=message):
            parse_selector(bad)


# ----------------------------------------------------------------------------------------------
# roles in scan.yaml


@pytest.fixture(scope="module")
def gray_scan():
    return simulate_scene("spheres", "gray7inv+whiteblack+random3", "small", SimOptions(seed=4), device="cpu")


def test_simulated_scans_write_roles(gray_scan, tmp_path):
    gray_scan.save(tmp_path / "s")
    doc = yaml.safe_load((tmp_path / "s" / "scan.yaml").read_text())
    by_name = {f["name"]: f.get("role") for f in doc["frames"]}
    assert by_name["gc_col_b3_inv"] == {"kind": "gray", "axis": "col", "bit": 3, "inverse": True}
    assert by_name["white"] == "white" and by_name["rand20_0"] == {"kind": "random", "size": 20.0, "index": 0}
    back = load_scan(tmp_path / "s")
    assert back.roles == gray_scan.roles


def test_gray_code_with_other_names_decodes_once_roles_are_declared(gray_scan, tmp_path):
    """A scan whose Gray code frames are called gray_b0, gray_b1, ... (and its inverses gray_b0_inverse ...)."""
    folder = tmp_path / "renamed"
    gray_scan.save(folder)
    doc = yaml.safe_load((folder / "scan.yaml").read_text())
    for f in doc["frames"]:
        f.pop("role", None)
        f["name"] = f["name"].replace("gc_col_b", "gray_b").replace("_inv", "_inverse")
    (folder / "scan.yaml").write_text(yaml.safe_dump(doc))
    with pytest.raises(MissingFrames, match="gc-interp needs Gray code frames") as e:
        decode(load_scan(folder), "gc-interp")
    assert "no role (14 frames: gray_b0, gray_b0_inverse" in str(e.value)
    for f in doc["frames"]:
        if f["name"].startswith("gray_b"):
            bit = int(f["name"][6:].split("_")[0])
            f["role"] = {"kind": "gray", "axis": "col", "bit": bit, "inverse": f["name"].endswith("_inverse")}
    (folder / "scan.yaml").write_text(yaml.safe_dump(doc))
    renamed = load_scan(folder)
    ref, got = decode(gray_scan, "gc-interp"), decode(renamed, "gc-interp")
    assert got.frames == [n.replace("gc_col_b", "gray_b").replace("_inv", "_inverse") for n in ref.frames]
    assert np.array_equal(np.isnan(got.col), np.isnan(ref.col))
    assert np.allclose(got.col, ref.col, equal_nan=True, atol=1e-6)  # the images went through 8-bit PNG
    # and the role selector picks them for GC(5)
    assert renamed.select("gray:col:bit=0-4:noinv").names == [f"gray_b{k}" for k in range(5)]


def test_bad_role_in_scan_yaml_is_a_scan_error(gray_scan, tmp_path, capsys):
    folder = tmp_path / "bad"
    gray_scan.save(folder)
    doc = yaml.safe_load((folder / "scan.yaml").read_text())
    doc["frames"][2]["role"] = {"kind": "gray", "axis": "col"}
    (folder / "scan.yaml").write_text(yaml.safe_dump(doc))
    with pytest.raises(ScanError, match=r"scan.yaml: .*frame 'gc_col_b1': a gray role needs bit"):
        load_scan(folder)
    assert cli_main(["info", str(folder)]) == 2
    err = capsys.readouterr().err
    assert "frame 'gc_col_b1': a gray role needs bit" in err and "Traceback" not in err
    doc["frames"][2]["role"] = None
    (folder / "scan.yaml").write_text(yaml.safe_dump(doc))
    with pytest.raises(ScanError, match=r"frame 2 \('gc_col_b1'\) has an empty role"):
        load_scan(folder)


def test_info_shows_roles_and_frames_select_by_role(gray_scan, tmp_path, capsys):
    gray_scan.save(tmp_path / "s")
    assert cli_main(["info", str(tmp_path / "s"), "--roles"]) == 0
    out = capsys.readouterr().out
    assert "gray:col:bit=0-6 (+inv)  14 frames: gc_col_b0" in out
    assert "random:size=20           1 frame: rand20_0" in out
    assert "gc_col_b2_inv  gray:col:bit=2:inv" in out
    assert cli_main(["info", str(tmp_path / "s"), "--frames", "gray:col:bit=0-2:noinv,white,black"]) == 0
    assert "frames: 5," in capsys.readouterr().out
    assert cli_main(["info", str(tmp_path / "s"), "--frames", "phase:col"]) == 2
    assert "no frame has a role matching 'phase:col'; the frames by role: gray:col:bit=0-6 (+inv); white" in capsys.readouterr().err


# ----------------------------------------------------------------------------------------------
# the NeSS layout: the authors' tags


W_TAGS = {  # tag -> pattern maker (projector width w, height h)
    "arr20r0": lambda w, h: RANDOM(w, h)["rand20_0"],
    "arr20r1": lambda w, h: RANDOM(w, h)["rand20_1"],
    "arr20r0inv": lambda w, h: 1.0 - RANDOM(w, h)["rand20_0"],
    "arr10r0": lambda w, h: RANDOM(w, h)["rand10_0"],
    "arr5r0": lambda w, h: RANDOM(w, h)["rand5_0"],
    "arr5r1": lambda w, h: RANDOM(w, h)["rand5_1"],
    **{f"gc{k}": (lambda k: lambda w, h: gray_code(w, h, 7).patterns[k])(k) for k in range(7)},
    **{f"gc{k}inv": (lambda k: lambda w, h: 1.0 - gray_code(w, h, 7).patterns[k])(k) for k in range(7)},
    "uni200": lambda w, h: np.full((h, w), 200 / 255, np.float32),
    "uni100": lambda w, h: np.full((h, w), 100 / 255, np.float32),
    "extra0": lambda w, h: np.full((h, w), 0.5, np.float32),
}


def RANDOM(w, h):
    ps = random_binary(w, h, per_scale=2, seed=7)
    return dict(zip(ps.names, ps.patterns))


def authors_phase(w, h, period, k):
    """The NeSS authors' 3-step convention: 8-bit levels 100..200, cos(2 pi u / P - pi + d_k), d = -120, 0, 120 deg."""
    u = np.arange(w, dtype=np.float64)
    d = (-2 * math.pi / 3, 0.0, 2 * math.pi / 3)[k]
    prof = (150.0 + 50.0 * np.cos(2 * math.pi * u / period - math.pi + d)) / 255.0
    return np.broadcast_to(prof, (h, w)).astype(np.float32)


for _p in (48, 70, 640, 80):
    for _k in range(3):
        W_TAGS[f"pm{_p}n3i{_k}"] = (lambda p, k: lambda w, h: authors_phase(w, h, p, k))(_p, _k)

AUTHORS_ORDER = (["arr20r0", "arr20r0inv", "arr20r1", "arr10r0", "arr5r0", "arr5r1"]
                 + [t for k in range(7) for t in (f"gc{k}", f"gc{k}inv")]
                 + [f"pm{p}n3i{k}" for p in (640, 80, 70, 48) for k in range(3)] + ["uni200", "uni100", "extra0"])


@pytest.fixture(scope="module")
def ness_dir(tmp_path_factory):
    """A synthetic scan in the NeSS layout (config.ini + img/ + pat/ + gt/) covering every kind of tag,
    simulated on the small rig without lens distortion (config.ini holds none)."""
    cam0, proj0 = make_rig("small")
    cam = Camera(cam0.width, cam0.height, cam0.K)
    proj = Projector(proj0.width, proj0.height, proj0.K, R=proj0.R, T=proj0.T)
    tags = list(W_TAGS)
    random.Random(3).shuffle(tags)  # the files' order must not matter
    pats = PatternSet(np.stack([W_TAGS[t](proj.width, proj.height) for t in tags]), tags)
    # no noise: the authors' phase patterns use levels 100..200 only, which N-PMP (1 px tolerance) does not survive
    scan = simulate(build_scene("torus"), cam, proj, pats, SimOptions(noise=False), depth_range=(450.0, 1100.0),
                    device="cpu")
    folder = tmp_path_factory.mktemp("ness") / "scene_00"
    for sub in ("img", "pat", "gt"):
        (folder / sub).mkdir(parents=True)
    (folder / "config.ini").write_text("\n".join([
        "[RawCalib]", f"img_size = {cam.width},{cam.height}", f"pat_size = {proj.width},{proj.height}",
        f"img_intrin = {cam.fx},{cam.fy},{cam.cx},{cam.cy}", f"pat_intrin = {proj.fx},{proj.fy},{proj.cx},{proj.cy}",
        "ext_rot = " + ",".join(repr(float(x)) for x in proj.R.ravel()),
        "ext_tran = " + ",".join(repr(float(x)) for x in proj.T), "z_range = 450.0,1100.0"]) + "\n")
    for i, t in enumerate(tags):
        cv2.imwrite(str(folder / "img" / f"img_{t}.png"), np.rint(scan.images[i] * 255).astype(np.uint8))
        cv2.imwrite(str(folder / "pat" / f"pat_{t}.png"), np.rint(scan.patterns[i] * 255).astype(np.uint8))
    write_depth_png(folder / "gt" / "depth.png", scan.gt_depth)
    cv2.imwrite(str(folder / "gt" / "mask_occ.png"), scan.mask.astype(np.uint8) * 255)
    return folder


def test_ness_tags_map_to_roles_in_the_authors_order(ness_dir):
    scan = load_scan(ness_dir)
    assert scan.names == AUTHORS_ORDER
    role = dict(zip(scan.names, scan.roles))
    assert role["arr20r0inv"] == FrameRole("random", size=20.0, index=0, inverse=True)
    assert role["gc3inv"] == FrameRole("gray", axis="col", bit=3, inverse=True)
    assert role["pm48n3i2"] == FrameRole("phase", axis="col", period=48.0, step=2, steps=3)
    assert role["uni200"] == FrameRole("uniform", level=200 / 255) and role["extra0"] is None
    # incremental mode takes a prefix: the random patterns come first, coarse to fine
    assert scan.select("random:noinv").names == ["arr20r0", "arr20r1", "arr10r0", "arr5r0", "arr5r1"]
    assert scan.select("gray:bit=0-2:noinv").names == ["gc0", "gc1", "gc2"]


@pytest.mark.parametrize("method,frames,mae", [
    ("gc-interp", "gray", 1.0),                          # 7 bits with inverses
    ("gc-interp", "gray:noinv,uniform", 1.0),            # threshold from uni200 and uni100
    ("npmp", None, 1.5),                                 # the authors' 3-step convention at 48 and 70 px
    ("hpmp", None, 3.0),
    ("ps", None, 15.0),                                  # one 640 px period on 15 grey levels of modulation
])
def test_every_decoder_works_on_ness_tags(ness_dir, method, frames, mae):
    scan = load_scan(ness_dir)
    depth, _, dec = reconstruct_depth(scan, method, frames=frames)
    m = depth_metrics(depth, scan.gt_depth, scan.mask)
    assert m["mae"] < mae and m["completeness"] > 0.9, m
    if frames == "gray:noinv,uniform":
        assert dec.frames[-2:] == ["uni200", "uni100"] and "gc0inv" not in dec.frames


def test_ness_info_groups_tags_by_role(ness_dir, capsys):
    assert cli_main(["info", str(ness_dir)]) == 0
    out = capsys.readouterr().out
    for line in ("random:size=20 (1 inverse)", "3 frames: arr20r0, arr20r0inv, arr20r1",
                 "gray:col:bit=0-6 (+inv)", "phase:col:period=48:steps=3 (step=0-2)",
                 "uniform:level=0.784314", "no role", "extra0"):
        assert line in out, line
    assert out.count("\n    ") == 11  # 11 groups, not one per tag


def test_ness_tag_with_impossible_values(ness_dir, tmp_path):
    import shutil

    bad = tmp_path / "bad"
    shutil.copytree(ness_dir, bad)
    (bad / "pat" / "pat_pm48n3i2.png").rename(bad / "pat" / "pat_pm48n3i5.png")
    (bad / "img" / "img_pm48n3i2.png").rename(bad / "img" / "img_pm48n3i5.png")
    with pytest.raises(ScanError, match="NeSS frame tag 'pm48n3i5': step must be in 0..steps-1"):
        load_scan(bad)
