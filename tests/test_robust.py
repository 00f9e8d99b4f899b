"""Nothing lost, nothing misreported: run identity on resume, refused overwrites, outputs that appear together or
not at all, SIGINT/SIGTERM/SIGKILL and resume, one-line errors for bad paths, checkpoints and calibration files,
numeric options checked at the door, and scans whose problem is named."""
import dataclasses
import json
import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
import torch

from slwarp.cli import main as cli_main
from slwarp.evaluation.outputs import OutputError, check_output_folder, staged_outputs, write_depth
from slwarp.neural.config import preset
from slwarp.neural.reconstruct import reconstruct
from slwarp.neural.training.checkpoint import CheckpointError, CheckpointExists, RunMismatch, read_checkpoint
from slwarp.neural.training import Trainer, TrainingInterrupted
from slwarp.scans.scan import Scan, ScanError, load_scan
from slwarp.sim.simulate import SimOptions, simulate_scene


@pytest.fixture(scope="module")
def scan():
    return simulate_scene("spheres", "random6", rig="small", options=SimOptions(seed=3))


def tiny(**kw):
    # the sphere start skips the depth search: what these tests check does not depend on it, and it is slow
    return preset("tiny", device="cpu", **{"iters": 20, "init": "sphere", "init_iters": 10, "checkpoint_every": 10,
                                           "log_every": 5, "rays": 64, "mc_resolution": 32, **kw})


def params_vector(trainer):
    return torch.cat([p.detach().reshape(-1) for p in list(trainer.field.parameters())
                      + list(trainer.renderer.variance.parameters())])


# --- 1, 2: run identity and overwrites ------------------------------------------------------------


def test_resume_refuses_another_run_and_names_each_difference(scan, tmp_path):
    Trainer(scan, tiny(), out_dir=tmp_path, progress=False).train(iters=10)
    cases = [
        (scan.select("0:3"), tiny(), {}, "frames: 6 (rand"),  # fewer frames
        (scan, tiny(lr=1e-3), {}, "option lr: 0.0005 in the checkpoint, 0.001 now"),
        (scan, tiny(seed=1), {}, "option seed: 0 in the checkpoint, 1 now"),
        (scan, tiny(), {"depth_range": (500.0, 1000.0)}, "depth range (mm)"),
    ]
    for s, cfg, kw, expect in cases:
        with pytest.raises(RunMismatch) as e:
            Trainer(s, cfg, out_dir=tmp_path, resume=True, progress=False, **kw)
        assert expect in str(e.value) and "--overwrite" in str(e.value)
    # the same frames with other content
    changed = dataclasses.replace(scan, images=scan.images.copy())
    changed.images[2] *= 0.5
    with pytest.raises(RunMismatch, match="frame content: .*changed in rand"):
        Trainer(changed, tiny(), out_dir=tmp_path, resume=True, progress=False)
    # the options marked resumable may change: more iterations, logging, extraction
    tr = Trainer(scan, tiny(iters=40, log_every=2, mc_resolution=48), out_dir=tmp_path, resume=True, progress=False)
    assert tr.iteration == 10


def test_new_run_over_a_checkpoint_is_refused_unless_overwrite(scan, tmp_path):
    Trainer(scan, tiny(), out_dir=tmp_path, progress=False).train(iters=10)
    before = (tmp_path / "checkpoint.pt").read_bytes()
    with pytest.raises(CheckpointExists, match="--resume continues it, --overwrite starts again"):
        Trainer(scan, tiny(), out_dir=tmp_path, progress=False)
    assert (tmp_path / "checkpoint.pt").read_bytes() == before
    tr = Trainer(scan, tiny(), out_dir=tmp_path, overwrite=True, progress=False)
    tr.train(iters=5)
    assert read_checkpoint(tmp_path / "checkpoint.pt")["iteration"] == 5


def test_cli_says_when_the_refinement_is_skipped_for_the_model_misfit(scan, tmp_path, capsys):
    """--refine-max-misfit below the scan's misfit: the refinement is skipped, the CLI says why and how to force it,
    timings.json records the misfit and the decision."""
    folder, out = tmp_path / "scan", tmp_path / "out"
    scan.save(folder)
    fast = ["--preset", "tiny", "--device", "cpu", "--init", "sphere", "--iters", "5", "--rays", "64",
            "--mc-resolution", "16", "--min-confidence", "0", "--quiet"]
    assert cli_main(["reconstruct", str(folder), "--out", str(out), *fast, "--refine-range", "1",
                     "--refine-max-misfit", "0.0001"]) == 0
    printed = capsys.readouterr().out
    t = json.loads((out / "timings.json").read_text())
    assert t["refined"] is False and t["refine_misfit"] > 0.0001
    assert f"photometric refinement skipped: the pattern model's misfit at the field's depth is {t['refine_misfit']:.4f}" in printed
    assert "--refine-max-misfit 0 refines regardless" in printed


def test_cli_resume_refuses_changed_frames_and_new_run_refuses_a_checkpoint(scan, tmp_path, capsys):
    folder, out = tmp_path / "scan", tmp_path / "out"
    scan.save(folder)
    fast = ["--preset", "tiny", "--device", "cpu", "--init", "sphere", "--iters", "5", "--rays", "64",
            "--mc-resolution", "16", "--min-confidence", "0", "--quiet"]
    assert cli_main(["reconstruct", str(folder), "--out", str(out), *fast]) == 0
    printed = capsys.readouterr().out
    # what became of each pixel: a line, the picture and the counts (every pixel once)
    assert "pixels: " in printed and "(pixel_fate.png)" in printed and (out / "pixel_fate.png").is_file()
    counts = json.loads((out / "timings.json").read_text())["pixels"]
    assert sum(counts.values()) == scan.camera.height * scan.camera.width
    before = {p.name: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    cases = [(["--resume", "--frames", "0:3"], "frames: 6 (rand20_0"),
             ([], "holds the checkpoint of an earlier run; --resume continues it, --overwrite starts again")]
    for extra, expect in cases:
        assert cli_main(["reconstruct", str(folder), "--out", str(out), *fast, *extra]) == 2
        err = capsys.readouterr().err
        assert expect in err and len(err.strip().splitlines()) == 1, err
    assert {p.name: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before  # nothing touched
    # --help lists what may change on resume (from the config's option metadata)
    from slwarp.cli import build_parser

    sub = next(a for a in build_parser(["reconstruct"])._actions if a.dest == "command").choices["reconstruct"]
    flagged = {a.option_strings[0] for a in sub._actions if a.help and "may change on resume" in a.help}
    assert {"--iters", "--log-every", "--mc-resolution", "--device"} <= flagged
    assert not {"--lr", "--seed", "--rays", "--frames"} & flagged


@pytest.mark.parametrize("content", [b"", b"garbage, not a zip", "truncated"])
def test_unreadable_checkpoint_is_a_one_line_error(scan, tmp_path, capsys, content):
    folder = tmp_path / "scan"
    scan.save(folder)
    ck = tmp_path / "out" / "train" / "checkpoint.pt"
    ck.parent.mkdir(parents=True)
    if content == "truncated":
        torch.save({"iteration": 3, "field": {"w": torch.zeros(1000)}}, ck)
        ck.write_bytes(ck.read_bytes()[:300])
    else:
        ck.write_bytes(content)
    with pytest.raises(CheckpointError, match="not a readable checkpoint"):
        read_checkpoint(ck)
    assert cli_main(["reconstruct", str(folder), "--out", str(tmp_path / "out"), "--preset", "tiny", "--device", "cpu",
                     "--resume", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "checkpoint.pt: not a readable checkpoint" in err and len(err.strip().splitlines()) == 1


# --- 3: outputs together or not at all ----------------------------------------------------------


def test_staged_outputs_replace_together_and_leave_nothing_on_failure(tmp_path):
    out = tmp_path / "run"
    with staged_outputs(out) as tmp:
        write_depth(tmp, np.ones((4, 5), np.float32))
        (tmp / "metrics.json").write_text("old")
    (out / "train").mkdir()
    (out / "train" / "checkpoint.pt").write_text("ck")
    with pytest.raises(RuntimeError):
        with staged_outputs(out) as tmp:
            write_depth(tmp, np.full((4, 5), 2.0, np.float32))
            raise RuntimeError("extraction failed")
    assert np.load(out / "depth.npy")[0, 0] == 1.0 and (out / "metrics.json").read_text() == "old"
    with staged_outputs(out) as tmp:  # a run without metrics: the old metrics.json does not linger beside it
        write_depth(tmp, np.full((4, 5), 3.0, np.float32))
    assert sorted(p.name for p in out.iterdir()) == ["depth.npy", "depth.png", "train"]
    assert np.load(out / "depth.npy")[0, 0] == 3.0 and (out / "train" / "checkpoint.pt").read_text() == "ck"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]  # no temporary folder left
    with pytest.raises(RuntimeError):
        with staged_outputs(tmp_path / "new" / "run"):
            raise RuntimeError("failed before writing")
    assert not (tmp_path / "new" / "run").exists()


def test_output_folder_that_is_a_file(tmp_path, scan, capsys):
    (tmp_path / "f").write_text("x")
    with pytest.raises(OutputError, match="is a file"):
        check_output_folder(tmp_path / "f")
    with pytest.raises(OutputError, match="lies under a file"):
        check_output_folder(tmp_path / "f" / "sub")
    folder = tmp_path / "scan"
    scan.save(folder)
    for out, msg in ((tmp_path / "f", "is a file"), (tmp_path / "f" / "sub", "lies under a file")):
        assert cli_main(["reconstruct", str(folder), "--out", str(out), "--preset", "tiny", "--device", "cpu",
                         "--quiet"]) == 2
        err = capsys.readouterr().err
        assert msg in err and len(err.strip().splitlines()) == 1


def test_failed_extraction_keeps_the_previous_outputs(scan, tmp_path, monkeypatch):
    import slwarp.neural.reconstruct as rec

    out = tmp_path / "run"
    reconstruct(scan, tiny(), out_dir=out, progress=False)
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    assert "metrics.json" in before and "depth.npy" in before

    def fail(*a, **k):
        raise RuntimeError("marching cubes failed")

    monkeypatch.setattr(rec, "extract_depth", fail)
    with pytest.raises(RuntimeError, match="marching cubes"):
        reconstruct(scan, tiny(iters=25), out_dir=out, resume=True, progress=False)
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]
    assert not list(out.rglob("*.tmp"))
    # a run that fails before its first checkpoint leaves no folder at all
    with pytest.raises(ScanError):
        reconstruct(scan, tiny(), out_dir=tmp_path / "fresh", depth_range=(500.0, float("inf")), progress=False)
    assert not (tmp_path / "fresh").exists()


def test_metrics_json_lists_the_frames_trained_on(scan, tmp_path):
    res = reconstruct(scan.select("0:4"), tiny(iters=5), out_dir=tmp_path / "run", progress=False)
    doc = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert doc["schema"] == "slwarp.metrics/1" and doc["method"] == "neural-sdf"
    assert doc["frames"] == scan.names[:4] and doc["metrics"]["mae"] == pytest.approx(res.metrics["mae"])


# --- 4: signals -----------------------------------------------------------------------------------


@pytest.mark.parametrize("sig, status", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_signal_saves_a_checkpoint_and_the_resumed_run_is_the_same(scan, tmp_path, sig, status):
    cfg = tiny()
    full = Trainer(scan, cfg, progress=False)
    full.train()

    def send(trainer):
        if trainer.iteration == 15:
            os.kill(os.getpid(), sig)

    tr = Trainer(scan, cfg, out_dir=tmp_path, progress=False)
    handler_before = signal.getsignal(sig)
    with pytest.raises(TrainingInterrupted) as e:
        tr.train(callback=send)
    assert e.value.exit_status == status and "--resume" in str(e.value)
    assert read_checkpoint(tmp_path / "checkpoint.pt")["iteration"] == 15  # the step boundary after the signal
    assert signal.getsignal(sig) is handler_before  # the caller's handler is back
    resumed = Trainer(scan, cfg, out_dir=tmp_path, resume=True, progress=False)
    resumed.train()
    assert torch.equal(params_vector(full), params_vector(resumed))


def test_cli_sigterm_exits_143_with_a_checkpoint_and_how_to_continue(scan, tmp_path):
    scan.save(tmp_path / "scan")
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "slwarp.cli", "reconstruct", str(tmp_path / "scan"), "--out", str(out),
                             "--preset", "tiny", "--device", "cpu", "--init", "sphere", "--iters", "100000", "--rays", "64",
                             "--checkpoint-every", "10", "--quiet"], stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.time() + 500
        while not (out / "train" / "checkpoint.pt").exists() and proc.poll() is None and time.time() < deadline:
            time.sleep(0.2)
        proc.send_signal(signal.SIGTERM)  # training is under way: its handler is installed
        err = proc.communicate(timeout=300)[1]
    finally:
        proc.kill()
    assert proc.returncode == 143, err
    assert "interrupted by SIGTERM" in err and "continue with --resume" in err
    assert read_checkpoint(out / "train" / "checkpoint.pt")["iteration"] >= 10
    assert sorted(p.name for p in out.iterdir()) == ["train"]  # no partial outputs
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "scan"]


def test_sigkill_mid_training_resumes_to_the_same_result(scan, tmp_path):
    """A child trains with a checkpoint every 10 iterations and is SIGKILLed after the checkpoint at 10; the
    resumed run ends where an uninterrupted one does, bit for bit."""
    scan.save(tmp_path / "scan")
    marker = tmp_path / "at15"
    child = textwrap.dedent(f"""
        import time, pathlib
        from slwarp.scans.scan import load_scan
        from slwarp.neural.config import preset
        from slwarp.neural.training import Trainer
        cfg = preset("tiny", device="cpu", iters=20, init="sphere", init_iters=10, checkpoint_every=10, log_every=5,
                     rays=64, mc_resolution=32)
        def hold(tr):
            if tr.iteration == 15:
                pathlib.Path({str(marker)!r}).write_text("x")
                time.sleep(600)
        Trainer(load_scan({str(tmp_path / "scan")!r}), cfg, out_dir={str(tmp_path / "run")!r}, progress=False).train(callback=hold)
    """)
    proc = subprocess.Popen([sys.executable, "-c", child])
    try:
        deadline = time.time() + 500
        while not marker.exists() and proc.poll() is None and time.time() < deadline:
            time.sleep(0.2)
        assert marker.exists(), "the child did not reach iteration 15"
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait()
    loaded = load_scan(tmp_path / "scan")
    resumed = Trainer(loaded, tiny(), out_dir=tmp_path / "run", resume=True, progress=False)
    assert resumed.iteration == 10
    resumed.train()
    full = Trainer(loaded, tiny(), progress=False)
    full.train()
    assert torch.equal(params_vector(full), params_vector(resumed))


# --- 5: disk full and read-only ---------------------------------------------------------------------


def _small_fs_available() -> str | None:
    """None when a user and mount namespace with a 64 KiB tmpfs can be made here, else why not."""
    if not sys.platform.startswith("linux"):
        return "tmpfs in a user namespace needs Linux"
    try:
        r = subprocess.run(["unshare", "--user", "--map-root-user", "--mount", "sh", "-c",
                            "d=$(mktemp -d) && mount -t tmpfs -o size=64k tmpfs $d && rmdir $d 2>/dev/null; true"],
                           capture_output=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired) as e:
        return f"unshare unavailable ({e})"
    return None if r.returncode == 0 and not r.stderr else f"no user/mount namespace here ({r.stderr.decode().strip()})"


def test_disk_full_and_read_only_are_one_line_errors(tmp_path):
    why = _small_fs_available()
    if why:
        pytest.skip(why)
    # a 64 KiB file system: the evaluation's error map does not fit
    scan = Scan(*_tiny_rig(), np.random.default_rng(0).uniform(0, 1, (2, 120, 160)), np.ones((2, 24, 32)),
                ["white", "w2"], gt_depth=np.full((120, 160), 600.0, np.float32))
    scan.save(tmp_path / "scan")
    np.save(tmp_path / "pred.npy", np.full((120, 160), 601.0, np.float32))
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    script = (f"mount -t tmpfs -o size=64k tmpfs {mnt} && head -c 60000 /dev/zero > {mnt}/filler && "
              f"{sys.executable} -m slwarp.cli evaluate {tmp_path / 'pred.npy'} {tmp_path / 'scan'} --out {mnt}/ev; "
              f"echo status=$?; ls -a {mnt}/ev 2>/dev/null; "
              f"mkdir -p {mnt}/ro && mount -o remount,ro {mnt} && "
              f"{sys.executable} -m slwarp.cli evaluate {tmp_path / 'pred.npy'} {tmp_path / 'scan'} --out {mnt}/ro; "
              "echo status=$?")
    r = subprocess.run(["unshare", "--user", "--map-root-user", "--mount", "sh", "-c", script], capture_output=True,
                       text=True, timeout=300)
    statuses = [line for line in r.stdout.splitlines() if line.startswith("status=")]
    assert statuses == ["status=2", "status=2"], r.stdout + r.stderr
    errors = [line for line in r.stderr.splitlines() if line.startswith("slwarp evaluate: error:")]
    assert len(errors) == 2 and "No space left on device" in errors[0] and "Read-only file system" in errors[1], r.stderr
    assert "Traceback" not in r.stderr


def test_checkpoint_on_a_full_disk_leaves_no_tmp(scan, tmp_path):
    if not os.path.exists("/dev/full"):
        pytest.skip("needs /dev/full")
    tr = Trainer(scan, tiny(init="sphere"), out_dir=tmp_path, progress=False)
    (tmp_path / "checkpoint.tmp").symlink_to("/dev/full")  # every write there fails with ENOSPC
    with pytest.raises(OSError, match="checkpoint"):
        tr.save_checkpoint()
    assert not (tmp_path / "checkpoint.tmp").exists() and not (tmp_path / "checkpoint.pt").exists()


def test_outputs_on_a_full_disk_name_the_folder_and_leave_nothing(tmp_path):
    if not os.path.exists("/dev/full"):
        pytest.skip("needs /dev/full")
    out = tmp_path / "run"
    with pytest.raises(OSError) as e:
        with staged_outputs(out) as tmp:
            (tmp / "depth.npy").symlink_to("/dev/full")  # every write there fails with ENOSPC
            write_depth(tmp, np.ones((64, 64), np.float32))
    assert "No space left on device" in str(e.value) and str(out) in str(e.value)
    assert list(tmp_path.iterdir()) == []


def _tiny_rig():
    from slwarp.scans.scanner import Camera, Projector, look_at_rotation

    cam = Camera(160, 120, np.array([[150.0, 0, 80], [0, 150, 60], [0, 0, 1]]))
    prj = Projector(32, 24, np.array([[30.0, 0, 16], [0, 30, 12], [0, 0, 1]]), R=look_at_rotation(np.array([-100.0, 0, 0]),
                    np.array([0.0, 0, 600])), T=np.array([100.0, 0, 0]))
    return cam, prj


def test_calibration_xml_errors_are_scan_errors(chessboard_path, tmp_path, capsys):
    folder = tmp_path / "procam"
    folder.mkdir()
    xml = folder / "calibration_result.xml"
    good = (chessboard_path / "calibration_result.xml").read_text()
    # truncated (OpenCV: SystemError) and a matrix whose size disagrees with its data (cv2.error)
    for bad in (good[: len(good) // 2], good.replace("<rows>3</rows>", "<rows>7</rows>", 1)):
        xml.write_text(bad)
        with pytest.raises(ScanError, match="calibration_result.xml"):
            load_scan(folder)
        assert cli_main(["info", str(folder)]) == 2
        err = capsys.readouterr().err
        assert "calibration_result.xml" in err and len(err.strip().splitlines()) == 1


# --- 6: numeric options at the door --------------------------------------------------------------------


@pytest.mark.parametrize("argv, expect", [
    (["--iters", "0"], "iters"), (["--iters", "-3"], "iters"), (["--rays", "0"], "rays"),
    (["--mc-resolution", "0"], "--mc-resolution: 0"), (["--min-confidence", "-0.5"], "--min-confidence: -0.5"),
    (["--device", "gpu"], "auto, cpu, cuda or cuda:N"), (["--device", "mps"], "auto, cpu, cuda or cuda:N"),
])
def test_numeric_options_are_checked_at_the_door(tmp_path, capsys, argv, expect):
    with pytest.raises(SystemExit) as e:
        cli_main(["reconstruct", str(tmp_path), "--out", str(tmp_path / "o"), "--preset", "tiny", *argv])
    assert e.value.code == 2 and expect in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_infinite_depth_range_is_refused(scan, tmp_path, capsys):
    scan.save(tmp_path / "scan")
    for text in ("500,inf", "nan,900"):
        assert cli_main(["reconstruct", str(tmp_path / "scan"), "--out", str(tmp_path / "o"), "--preset", "tiny",
                         "--device", "cpu", "--depth-range", text]) == 2
        assert "--depth-range needs 0 < NEAR < FAR" in capsys.readouterr().err
    with pytest.raises(ScanError, match="two finite numbers"):
        Trainer(scan, tiny(), depth_range=(500.0, float("inf")), progress=False)


# --- 7: scans whose problem is named --------------------------------------------------------------------


def test_bad_scans_name_what_is_wrong_and_which_frames(scan, tmp_path, capsys):
    black = dataclasses.replace(scan, images=np.zeros_like(scan.images))
    saturated = dataclasses.replace(scan, images=np.ones_like(scan.images))
    one_channel = dataclasses.replace(scan, patterns=scan.patterns * 0.114)  # blue only, read as gray
    cases = [
        (scan.select("0"), "only 1 frame (rand", None),
        (black, "all frames are black", None),
        (saturated, "all frames are saturated", None),
        # no start depth: the pattern blur cannot be fitted, the error says why the scan is suspect
        (one_channel, "span only 0.11 of full scale (a colour pattern with one channel?",
         np.full((scan.camera.height, scan.camera.width), np.nan, np.float32)),
    ]
    assert scan.problems() == []
    for i, (bad, expect, init_depth) in enumerate(cases):
        assert any(expect in p for p in bad.problems()), bad.problems()
        with pytest.raises(ScanError) as e:
            Trainer(bad, tiny(), progress=False, init_depth=init_depth)
        assert expect in str(e.value)
        bad.save(tmp_path / f"bad{i}")
        assert cli_main(["info", str(tmp_path / f"bad{i}")]) == 0
        out = capsys.readouterr().out
        assert "warning: " in out and expect in out
