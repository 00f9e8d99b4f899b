"""Files from others (issue #44): checkpoints load without running code, a scan's files are read from inside its
folder unless allowed, and each reader refuses what it does not accept (docs/inputs.md names these tests)."""
import json
import os
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import yaml

from slwarp.batch import scan_cost
from slwarp.cli import main as cli_main
from slwarp.evaluation.outputs import read_confidence
from slwarp.neural.training.checkpoint import FORMAT, CheckpointError, make_state, read_checkpoint
from slwarp.neural.config import ConfigError, load_config, preset
from slwarp.neural.training import Trainer
from slwarp.scans.patterns import gray_code
from slwarp.scans.scan import Scan, ScanError, inside_folder, load_scan, read_depth
from slwarp.scans.scanner import Camera, Projector, look_at_rotation
from slwarp.sim.simulate import SimOptions, simulate_scene


class CreatesFile:
    """Unpickled, it creates the file `marker`: what a hostile file does with a shell command, made visible."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def hostile_checkpoint(path: Path, marker: Path) -> Path:
    """A checkpoint with every key slwarp needs, one of whose history values runs code when unpickled."""
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"iteration": 5, "config": {}, "field": {}, "variance": {}, "optimizer": {},
                "generator": torch.zeros(8, dtype=torch.uint8), "n_frames": 2,
                "history": {"loss": [CreatesFile(marker)]}}, path)
    return path


def small_scan() -> Scan:
    rng = np.random.default_rng(0)
    cam = Camera(64, 48, [[60, 0, 31.5], [0, 60, 23.5], [0, 0, 1]])
    R = look_at_rotation(np.array([50.0, 0, 0]), np.array([0, 0, 500.0]))
    prj = Projector(80, 60, [[70, 0, 39.5], [0, 70, 29.5], [0, 0, 1]], R=R, T=-R @ np.array([50.0, 0, 0]))
    pats = gray_code(80, 60, 3)
    gt = rng.uniform(400, 900, (48, 64)).astype(np.float32)
    return Scan(cam, prj, rng.uniform(0, 1, (3, 48, 64)), pats.patterns, pats.names, depth_range=(300.0, 1000.0),
                gt_depth=gt, mask=rng.uniform(size=(48, 64)) > 0.3)


@pytest.fixture
def native(tmp_path):
    return small_scan().save(tmp_path / "scan")


def edit_yaml(folder: Path, fn) -> None:
    doc = yaml.safe_load((folder / "scan.yaml").read_text())
    fn(doc)
    (folder / "scan.yaml").write_text(yaml.safe_dump(doc))


def one_line_error(capsys, expect: str) -> str:
    err = capsys.readouterr().err
    assert expect in err and len(err.strip().splitlines()) == 1, err
    return err


# --- checkpoints ------------------------------------------------------------------------------------


def test_checkpoint_that_would_run_code_is_refused_unread(native, tmp_path, capsys):
    # the payload is live: unpickled the way slwarp used to read checkpoints, it creates its file
    hostile_checkpoint(tmp_path / "probe.pt", tmp_path / "probe-ran")
    torch.load(tmp_path / "probe.pt", weights_only=False)
    assert (tmp_path / "probe-ran").exists()

    marker = tmp_path / "ran"
    ck = hostile_checkpoint(tmp_path / "out" / "train" / "checkpoint.pt", marker)
    with pytest.raises(CheckpointError, match="refused unread: it refers to io.open"):
        read_checkpoint(ck)
    assert cli_main(["reconstruct", str(native), "--out", str(tmp_path / "out"), "--resume", "--preset", "tiny",
                     "--device", "cpu", "--quiet"]) == 2
    one_line_error(capsys, "checkpoint.pt: refused unread")
    assert not marker.exists()


def test_batch_resume_refuses_a_hostile_checkpoint_as_that_scans_failure(tmp_path, capsys):
    scans = tmp_path / "scans"
    for name in ("a", "b", "c"):
        small_scan().save(scans / name)
    edit_yaml(scans / "c", lambda d: d.update(mask="../a/mask.png"))  # another folder's file: c's own failure
    out, ran = tmp_path / "out", tmp_path / "ran"
    hostile_checkpoint(out / "a" / "train" / "checkpoint.pt", ran)
    # b's outputs are complete (resume skips it and reads its summary line from them), with a hostile depth.npy
    (out / "b").mkdir(parents=True)
    np.save(out / "b" / "depth.npy", np.array([CreatesFile(ran)], dtype=object), allow_pickle=True)
    (out / "b" / "timings.json").write_text(json.dumps({"total_s": 1.0, "iterations": 5}))
    (out / "b" / "config.yaml").write_text("{}\n")
    assert cli_main(["reconstruct", str(scans), "--out", str(out), "--resume", "--preset", "tiny", "--device", "cpu",
                     "--quiet"]) == 1
    rows = {r["name"]: r for r in json.loads((out / "summary.json").read_text())["scans"]}
    assert rows["a"]["status"] == "failed" and "checkpoint.pt: refused unread" in rows["a"]["error"]
    assert rows["b"]["status"] == "skipped" and "outputs unreadable" in rows["b"]["error"]
    assert rows["c"]["status"] == "failed" and "mask '../a/mask.png' leads outside the scan folder" in rows["c"]["error"]
    assert "failed: a (" in capsys.readouterr().out
    assert not ran.exists()


@pytest.fixture(scope="module")
def interrupted(tmp_path_factory):
    """(scan, config, parameters of an uninterrupted 20-iteration run, the checkpoint bytes at iteration 10)."""
    scan = simulate_scene("spheres", "random6", rig="small", options=SimOptions(seed=3))
    cfg = preset("tiny", device="cpu", iters=20, init="sphere", init_iters=10, checkpoint_every=10, log_every=5,
                 rays=64, mc_resolution=32)
    full = Trainer(scan, cfg, progress=False)
    full.train()
    folder = tmp_path_factory.mktemp("part")
    Trainer(scan, cfg, out_dir=folder, progress=False).train(iters=10)
    return scan, cfg, params(full), (folder / "checkpoint.pt").read_bytes()


def params(trainer) -> torch.Tensor:
    return torch.cat([p.detach().reshape(-1) for p in list(trainer.field.parameters())
                      + list(trainer.renderer.variance.parameters())])


def rewrite(folder: Path, data: bytes, fn) -> Path:
    """The checkpoint `data` in folder/checkpoint.pt, changed by fn(contents)."""
    path = folder / "checkpoint.pt"
    path.write_bytes(data)
    ck = torch.load(path, weights_only=True)
    fn(ck)
    torch.save(ck, path)
    return path


def test_checkpoint_of_the_previous_format_resumes_to_the_same_result(interrupted, tmp_path):
    scan, cfg, full, data = interrupted

    def previous(ck):  # as slwarp wrote them before the format key: no key, tuples
        assert ck.pop("format") == FORMAT
        ck["depth_range"] = tuple(ck["depth_range"])
        ck["volume"] = {k: tuple(v) for k, v in ck["volume"].items()}

    rewrite(tmp_path, data, previous)
    resumed = Trainer(scan, cfg, out_dir=tmp_path, resume=True, progress=False)
    assert resumed.iteration == 10
    resumed.train()
    assert torch.equal(params(resumed), full)
    assert read_checkpoint(tmp_path / "checkpoint.pt")["format"] == FORMAT  # written anew in this format


@pytest.mark.parametrize("change, expect", [
    (lambda ck: ck.update(format=FORMAT + 1), "written by a newer slwarp"),
    (lambda ck: ck.update(generator=torch.zeros(3)), "malformed generator state"),
    (lambda ck: ck.update(iteration="10"), "entry 'iteration' is a str"),
    (lambda ck: ck.pop("optimizer"), "missing ['optimizer']"),
    (lambda ck: ck["history"].update(steps=[1]), "its history holds"),
    (lambda ck: ck["identity"].pop("frames"), "a malformed run identity"),
    (lambda ck: ck.update(field={}), "does not fit this run's field"),
    (lambda ck: ck.update(init_depth=torch.zeros(7)), "its starting depth map has 7 pixels"),
])
def test_altered_checkpoint_is_a_one_line_checkpoint_error(interrupted, tmp_path, change, expect):
    scan, cfg, _, data = interrupted
    rewrite(tmp_path, data, change)
    with pytest.raises(CheckpointError) as e:
        Trainer(scan, cfg, out_dir=tmp_path, resume=True, progress=False)
    assert expect in str(e.value) and "\n" not in str(e.value)


def test_checkpoint_state_holds_tensors_and_plain_data_only():
    field, variance = torch.nn.Linear(2, 1), torch.nn.Linear(1, 1)
    kw = dict(iteration=3, config={"field": {"kind": "mlp"}}, field=field, variance=variance,
              optimizer=torch.optim.Adam(field.parameters()), generator_state=torch.Generator().get_state(),
              n_frames=2, volume={"lo": (0.0, 0.0, 0.0), "hi": (1.0, 1.0, 1.0)}, depth_range=(1.0, 2.0),
              history={"loss": [0.5]}, elapsed=np.float64(1.5), init_depth=None, pattern_blur=np.float32(0.5),
              identity={"frames": []})
    state = make_state(**kw)
    assert type(state["elapsed"]) is float and state["volume"]["lo"] == [0.0, 0.0, 0.0]
    # a numpy float is a float subclass that torch.load(weights_only=True) refuses: caught when writing
    with pytest.raises(TypeError, match=r"state\['history'\]\['loss'\]\[0\] is a numpy.float64"):
        make_state(**{**kw, "history": {"loss": [np.float64(0.5)]}})


# --- a scan's files: inside its folder ----------------------------------------------------------------


def test_scan_yaml_entry_outside_the_folder_is_refused_unless_allowed(native, tmp_path, capsys):
    outside = tmp_path / "elsewhere.png"
    image = yaml.safe_load((native / "scan.yaml").read_text())["frames"][1]["image"]
    outside.write_bytes((native / image).read_bytes())
    edit_yaml(native, lambda d: d["frames"][1].update(image="../elsewhere.png"))
    with pytest.raises(ScanError, match=r"scan.yaml: frames\[1\].image '../elsewhere.png' leads outside the scan folder"):
        load_scan(native)
    assert cli_main(["info", str(native)]) == 2
    one_line_error(capsys, "frames[1].image '../elsewhere.png' leads outside")
    # allowed by the caller: the option, or Python's keyword
    assert load_scan(native, outside_paths=True).names == small_scan().names
    assert cli_main(["info", str(native), "--allow-outside-paths"]) == 0
    capsys.readouterr()
    # an absolute path is refused the same way
    edit_yaml(native, lambda d: d["frames"][1].update(image=str(outside)))
    with pytest.raises(ScanError, match=r"frames\[1\].image '/.*elsewhere.png' leads outside"):
        load_scan(native)
    # allowed by the scan's own flag, unless the caller refuses outside paths whatever the scan says
    edit_yaml(native, lambda d: d.update(allow_outside_paths=True))
    assert len(load_scan(native)) == 3
    with pytest.raises(ScanError, match="whatever its allow_outside_paths says"):
        load_scan(native, outside_paths=False)
    assert cli_main(["decode", str(native), "--method", "gc", "--out", str(tmp_path / "dec"),
                     "--no-allow-outside-paths"]) == 2
    one_line_error(capsys, "leads outside the scan folder")
    edit_yaml(native, lambda d: d.update(allow_outside_paths="yes"))
    with pytest.raises(ScanError, match="allow_outside_paths must be true or false"):
        load_scan(native)


def test_links_out_of_the_scan_folder_are_refused(native, tmp_path, capsys):
    secret = tmp_path / "secret"
    secret.mkdir()
    np.save(secret / "depth.npy", np.full((48, 64), 500.0, np.float32))
    # a link inside the folder to a file outside: its real path decides
    (native / "gt_link.npy").symlink_to(secret / "depth.npy")
    edit_yaml(native, lambda d: d.update(gt_depth="gt_link.npy"))
    with pytest.raises(ScanError, match=r"gt_depth 'gt_link.npy' leads outside the scan folder \(to .*secret"):
        load_scan(native)
    assert np.all(load_scan(native, outside_paths=True).gt_depth == 500.0)
    # a link that stays inside is the folder's own file
    (native / "gt_link.npy").unlink()
    (native / "gt_link.npy").symlink_to(native / "gt_depth.npy")
    assert load_scan(native).gt_depth is not None
    # the mask through a linked folder; scan.yaml itself a link out
    (native / "linked").symlink_to(secret, target_is_directory=True)
    cv2.imwrite(str(secret / "mask.png"), np.full((48, 64), 255, np.uint8))
    edit_yaml(native, lambda d: d.update(mask="linked/mask.png"))
    with pytest.raises(ScanError, match="mask 'linked/mask.png' leads outside"):
        load_scan(native)
    (secret / "scan.yaml").write_text((native / "scan.yaml").read_text())
    (native / "scan.yaml").unlink()
    (native / "scan.yaml").symlink_to(secret / "scan.yaml")
    assert cli_main(["evaluate", str(native / "gt_depth.npy"), str(native), "--out", str(tmp_path / "ev")]) == 2
    one_line_error(capsys, "scan.yaml: a link to")
    assert inside_folder(native / "images", native) and not inside_folder(native / "linked" / "x", native)


def test_scan_yaml_entry_that_is_not_a_path(native):
    edit_yaml(native, lambda d: d["frames"][0].update(pattern=5))
    with pytest.raises(ScanError, match=r"frames\[0\].pattern must be a file path relative to the scan folder, got 5"):
        load_scan(native)


def write_ness(folder: Path, scan: Scan) -> None:
    cam, prj = scan.camera, scan.projector
    (folder / "img").mkdir(parents=True)
    (folder / "pat").mkdir()
    for i, (im, pat) in enumerate(zip(scan.images, scan.patterns)):
        cv2.imwrite(str(folder / "img" / f"img_gc{i}.png"), np.round(im * 255).astype(np.uint8))
        cv2.imwrite(str(folder / "pat" / f"pat_gc{i}.png"), np.round(pat * 255).astype(np.uint8))
    nums = lambda a: ",".join(f"{x:.9g}" for x in np.ravel(a))  # noqa: E731
    (folder / "config.ini").write_text(
        f"[RawCalib]\nimg_size = {cam.width},{cam.height}\npat_size = {prj.width},{prj.height}\n"
        f"img_intrin = {cam.fx},{cam.fy},{cam.cx},{cam.cy}\npat_intrin = {prj.fx},{prj.fy},{prj.cx},{prj.cy}\n"
        f"ext_rot = {nums(prj.R)}\next_tran = {nums(prj.T)}\n")


def test_ness_layout_refuses_links_out_and_reports_a_stray_percent(tmp_path):
    folder, secret = tmp_path / "ness", tmp_path / "secret.png"
    write_ness(folder, small_scan())
    assert len(load_scan(folder)) == 3
    (folder / "img" / "img_gc1.png").rename(secret)
    (folder / "img" / "img_gc1.png").symlink_to(secret)
    with pytest.raises(ScanError, match="ness: image 'img/img_gc1.png' leads outside the scan folder"):
        load_scan(folder)
    assert len(load_scan(folder, outside_paths=True)) == 3
    text = (folder / "config.ini").read_text()
    (folder / "config.ini").write_text(text.replace("ext_tran = ", "ext_tran = 5%, "))
    with pytest.raises(ScanError, match=r"config.ini: \[RawCalib\] ext_tran is not a list of numbers"):
        load_scan(folder, outside_paths=True)
    (folder / "config.ini").rename(tmp_path / "config.ini")
    (folder / "config.ini").symlink_to(tmp_path / "config.ini")
    with pytest.raises(ScanError, match="ness: config.ini leads outside"):
        load_scan(folder)


def write_procam(folder: Path, scan: Scan) -> None:
    cam, prj = scan.camera, scan.projector
    (folder / "graycode_pattern").mkdir(parents=True)
    (folder / "capture_0").mkdir()
    fs = cv2.FileStorage(str(folder / "calibration_result.xml"), cv2.FILE_STORAGE_WRITE)
    for key, value in (("cam_int", cam.K), ("cam_dist", np.zeros((1, 5))), ("proj_int", prj.K),
                       ("proj_dist", np.zeros((1, 5))), ("rotation", prj.R), ("translation", prj.T.reshape(3, 1))):
        fs.write(key, np.asarray(value, np.float64))
    fs.release()
    for i, (im, pat) in enumerate(zip(scan.images, scan.patterns)):
        cv2.imwrite(str(folder / "capture_0" / f"graycode_{i:02d}.png"), np.round(im * 255).astype(np.uint8))
        cv2.imwrite(str(folder / "graycode_pattern" / f"pattern_{i:02d}.png"), np.round(pat * 255).astype(np.uint8))


def test_procam_layout_refuses_links_out(tmp_path):
    folder = tmp_path / "procam"
    write_procam(folder, small_scan())
    assert len(load_scan(folder)) == 3
    (tmp_path / "elsewhere").mkdir()
    with pytest.raises(ScanError, match="procam: capture '../elsewhere' leads outside the scan folder"):
        load_scan(folder, capture="../elsewhere")
    (folder / "graycode_pattern").rename(tmp_path / "patterns")
    (folder / "graycode_pattern").symlink_to(tmp_path / "patterns", target_is_directory=True)
    with pytest.raises(ScanError, match="pattern 'graycode_pattern/pattern_00.png' leads outside"):
        load_scan(folder)
    assert len(load_scan(folder, outside_paths=True)) == 3
    (folder / "calibration_result.xml").rename(tmp_path / "calibration.xml")
    (folder / "calibration_result.xml").symlink_to(tmp_path / "calibration.xml")
    with pytest.raises(ScanError, match="procam: calibration_result.xml leads outside"):
        load_scan(folder)


# --- the readers: what each refuses -------------------------------------------------------------------


def test_npy_with_objects_is_refused_without_unpickling(native, tmp_path, capsys):
    ran = tmp_path / "ran"
    np.save(native / "gt_depth.npy", np.array([CreatesFile(ran)], dtype=object), allow_pickle=True)
    np.save(tmp_path / "probe.npy", np.array([CreatesFile(tmp_path / "probe-ran")], dtype=object), allow_pickle=True)
    np.load(tmp_path / "probe.npy", allow_pickle=True)  # the payload is live when unpickled
    assert (tmp_path / "probe-ran").exists()
    with pytest.raises(ScanError, match="gt_depth is not a readable .npy array .*allow_pickle=False"):
        load_scan(native)
    # the confidence map evaluate reads
    np.save(tmp_path / "pred.npy", np.full((48, 64), 600.0, np.float32))
    np.save(tmp_path / "conf.npy", np.array([CreatesFile(ran)], dtype=object), allow_pickle=True)
    with pytest.raises(ValueError, match="conf.npy: not a numpy array file"):
        read_confidence(tmp_path / "conf.npy")
    assert not ran.exists()


def test_npz_and_non_numbers_under_a_npy_name_are_refused(tmp_path):
    ran = tmp_path / "ran"
    np.savez(tmp_path / "gt.npz", depth=np.array([CreatesFile(ran)], dtype=object))
    os.replace(tmp_path / "gt.npz", tmp_path / "gt.npy")
    with pytest.raises(ScanError, match="gt_depth is an .npz archive, not a .npy array"):
        read_depth(tmp_path / "gt.npy", "gt_depth")
    np.save(tmp_path / "words.npy", np.array([["a", "b"], ["c", "d"]]))
    with pytest.raises(ScanError, match="holds <U1 values, not numbers"):
        read_depth(tmp_path / "words.npy", "gt_depth")
    assert not ran.exists()


def test_yaml_with_python_tags_is_refused(native, tmp_path, capsys):
    ran = tmp_path / "ran"
    tag = f"!!python/object/apply:io.open ['{ran}', 'w']"
    yaml.unsafe_load(tag.replace(str(ran), str(tmp_path / "probe-ran")))  # the payload is live when constructed
    assert (tmp_path / "probe-ran").exists()
    text = (native / "scan.yaml").read_text()
    (native / "scan.yaml").write_text(text.replace("units: mm", f"units: {tag}"))
    with pytest.raises(ScanError, match="scan.yaml: not valid YAML .*could not determine a constructor"):
        load_scan(native)
    assert scan_cost(native) is None  # the batch's planner reads scan.yaml safely too
    (tmp_path / "cfg.yaml").write_text(f"field: {tag}\n")
    with pytest.raises(ConfigError, match="cfg.yaml: not valid YAML"):
        load_config(tmp_path / "cfg.yaml")
    assert not ran.exists()


def test_corrupt_ply_mesh_is_refused(tmp_path):
    from slwarp.sim.scenes import load_mesh_objects

    (tmp_path / "bad.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99\n")
    with pytest.raises(ValueError, match="bad.ply"):
        load_mesh_objects([tmp_path / "bad.ply"])


def test_images_are_read_as_png_or_tiff_only(native, capsys):
    frames = yaml.safe_load((native / "scan.yaml").read_text())["frames"]
    first, second = native / frames[0]["image"], native / frames[1]["image"]
    from_png = load_scan(native).images[0]
    tiff = first.with_suffix(".tif")
    assert cv2.imwrite(str(tiff), cv2.imread(str(first), cv2.IMREAD_UNCHANGED))
    first.unlink()
    edit_yaml(native, lambda d: d["frames"][0].update(image=tiff.relative_to(native).as_posix()))
    assert np.array_equal(load_scan(native).images[0], from_png)
    # a JPEG under a PNG name: OpenCV would decode it by its content; slwarp refuses it
    assert cv2.imwrite(str(second.with_suffix(".jpg")), np.zeros((48, 64), np.uint8))
    second.with_suffix(".jpg").replace(second)
    assert cli_main(["info", str(native)]) == 2
    one_line_error(capsys, "image of frame 1 is unreadable or corrupt (not a PNG or TIFF file")
