"""`slwarp reconstruct SCAN` as two processes (slwarp.cli.loader): the scan loaded beside the imports, the command
returning with the child's status once its files are written; the same depth map as one process, bad scans
reported as before, signals reaching the child, a child's crash giving its status."""
import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from slwarp.cli import loader
from slwarp.scans.scan import ScanError, load_scan
from slwarp.scans.scanner import camera_rays
from slwarp.sim.simulate import SimOptions, simulate_scene

REPO = Path(__file__).resolve().parents[1]
TINY = ["--preset", "tiny", "--device", "cpu", "--iters", "3", "--init-iters", "2", "--mc-resolution", "32",
        "--rays", "64", "--quiet"]


@pytest.fixture(scope="module")
def scan_dir(tmp_path_factory):
    folder = tmp_path_factory.mktemp("loader") / "scan"
    simulate_scene("spheres", "random6", rig="small", options=SimOptions(seed=5)).save(folder)
    return folder


def command(args, env=None, **kw):
    """`python -m slwarp ARGS` (the console command's entry(), which may fork) as a subprocess."""
    return subprocess.Popen([sys.executable, "-m", "slwarp", *map(str, args)], cwd=REPO,
                            env={**os.environ, **(env or {})}, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, **kw)


def test_two_processes_give_the_depth_map_of_one(scan_dir, tmp_path):
    timeline = tmp_path / "timeline.jsonl"
    runs = {}
    for split in ("1", "0"):
        out = tmp_path / f"out{split}"
        p = command(["reconstruct", scan_dir, "--out", out, *TINY],
                    env={"SLWARP_LOADER": split, "SLWARP_TIMELINE": str(timeline) if split == "1" else ""})
        stdout, stderr = p.communicate(timeout=600)
        assert p.returncode == 0, stderr
        assert "wrote" in stdout
        runs[split] = out
    # every file there when the command returned, the depth map the same
    assert sorted(p.name for p in runs["1"].iterdir()) == sorted(p.name for p in runs["0"].iterdir())
    np.testing.assert_array_equal(np.load(runs["1"] / "depth.npy"), np.load(runs["0"] / "depth.npy"))
    marks = dict(json.loads(timeline.read_text().splitlines()[-1])["marks"])
    assert {"imports", "scan loaded", "reconstructed", "exit"} <= set(marks)


def test_the_scans_problems_found_by_the_loader_are_the_warnings_of_one_process(scan_dir, tmp_path):
    import cv2

    broken = tmp_path / "scan"
    shutil.copytree(scan_dir, broken)
    first = sorted((broken / "images").iterdir())[0]
    cv2.imwrite(str(first), np.zeros_like(cv2.imread(str(first), cv2.IMREAD_UNCHANGED)))  # a black frame
    warnings = {}
    for split in ("1", "0"):
        p = command(["reconstruct", broken, "--out", tmp_path / f"out{split}", *TINY], env={"SLWARP_LOADER": split})
        _, stderr = p.communicate(timeout=600)
        assert p.returncode == 0, stderr
        warnings[split] = [line for line in stderr.splitlines() if line.startswith("warning:")]
    assert any("black" in line for line in warnings["0"])
    assert warnings["1"] == warnings["0"]


def test_a_scan_the_loader_cannot_read_is_a_one_line_error(scan_dir, tmp_path):
    broken = tmp_path / "broken"
    shutil.copytree(scan_dir, broken)
    images = sorted((broken / "images").iterdir())
    images[0].unlink()
    p = command(["reconstruct", broken, "--out", tmp_path / "out", *TINY])
    stdout, stderr = p.communicate(timeout=300)
    assert p.returncode == 2, stderr
    assert stderr.strip().splitlines() == [f"slwarp reconstruct: error: image of frame 0 not found: "
                                           f"{images[0]}"]
    assert not (tmp_path / "out").exists()


def _child_of(pid: int, timeout: float = 60.0) -> int:
    """The one child process of `pid` (Linux: /proc)."""
    deadline = time.time() + timeout
    while time.time() < deadline:
        kids = Path(f"/proc/{pid}/task/{pid}/children").read_text().split()
        if kids:
            return int(kids[0])
        time.sleep(0.05)
    raise AssertionError(f"process {pid} started no child")


def _alive(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except FileNotFoundError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def _training(scan_dir, out, checkpointed: bool = True):
    """(the command, its child): a long tiny-preset training, once its first checkpoint is written when
    `checkpointed`."""
    p = command(["reconstruct", scan_dir, "--out", out, "--preset", "tiny", "--device", "cpu", "--init", "sphere",
                 "--iters", "100000", "--rays", "64", "--checkpoint-every", "10", "--quiet"])
    child = _child_of(p.pid)
    deadline = time.time() + 500
    while checkpointed and not (out / "train" / "checkpoint.pt").exists() and p.poll() is None \
            and time.time() < deadline:
        time.sleep(0.2)
    return p, child


def _gone(pid: int, timeout: float) -> bool:
    deadline = time.time() + timeout
    while _alive(pid) and time.time() < deadline:
        time.sleep(0.1)
    return not _alive(pid)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="finds the child process through /proc")
def test_sigterm_to_the_command_reaches_the_child_which_keeps_a_checkpoint(scan_dir, tmp_path):
    out = tmp_path / "out"
    p, child = _training(scan_dir, out)
    try:
        p.send_signal(signal.SIGTERM)  # to the command alone, as `kill PID` or a job scheduler sends it
        stderr = p.communicate(timeout=300)[1]
    finally:
        p.kill()
    assert p.returncode == 143, stderr
    assert "interrupted by SIGTERM" in stderr and "continue with --resume" in stderr
    assert (out / "train" / "checkpoint.pt").exists()
    assert _gone(child, 60)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="finds the child process through /proc")
def test_a_child_killed_without_a_status_gives_the_signals_status(scan_dir, tmp_path):
    p, child = _training(scan_dir, tmp_path / "out", checkpointed=False)
    try:
        time.sleep(1.0)
        os.kill(child, signal.SIGKILL)
        p.communicate(timeout=120)
    finally:
        p.kill()
    assert p.returncode == 128 + signal.SIGKILL


def _args(scans, per_device=None):
    return argparse.Namespace(scans=[str(s) for s in scans], per_device=per_device)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the command splits on Linux only")
def test_only_the_console_command_with_one_scan_splits(scan_dir, tmp_path, monkeypatch):
    monkeypatch.setattr(loader, "_may_fork", False)
    assert loader.splits(_args([scan_dir])) is None  # main() called by a program or a test never forks
    monkeypatch.setattr(loader, "_may_fork", True)
    monkeypatch.delenv("SLWARP_LOADER", raising=False)
    monkeypatch.delenv("WORLD_SIZE", raising=False)
    assert loader.splits(_args([scan_dir])).single
    assert loader.splits(_args([scan_dir], per_device=1)) is None
    assert loader.splits(_args([scan_dir.parent])) is None  # a folder of scans: a batch
    assert loader.splits(_args([tmp_path / "missing"])) is None  # reported by the command itself
    monkeypatch.setenv("SLWARP_LOADER", "0")
    assert loader.splits(_args([scan_dir])) is None


def test_the_pipe_carries_the_scan_its_rays_and_errors(scan_dir, monkeypatch):
    from slwarp.scans import scanner

    scan = load_scan(scan_dir)
    rays = camera_rays(scan.camera) + 0.0  # a copy: cache_rays must place this one
    problems = ["2 of 6 frames are black"]
    for message in [("scan", (scan, rays, problems)), ("error", loader._picklable(ScanError(f"{scan_dir}: broken")))]:
        r, w = os.pipe()
        ahead = loader.ScanAhead(r)
        sender = threading.Thread(target=lambda: (loader._send(w, message), os.close(w)))
        sender.start()
        scanner._RAYS_CACHE.clear()
        monkeypatch.setattr(scanner, "_ray_grid", None)  # the received grid is used, never computed again
        if message[0] == "error":
            with pytest.raises(ScanError, match="broken"):
                ahead.scan()
        else:
            got = ahead.scan()
            np.testing.assert_array_equal(got.images, scan.images)
            assert got.names == scan.names
            np.testing.assert_array_equal(camera_rays(got.camera), rays)
            assert ahead.problems == problems
        sender.join()
        monkeypatch.undo()
    # a loader that ends without sending: a clear error where the scan is asked for
    r, w = os.pipe()
    os.close(w)
    with pytest.raises(RuntimeError, match="could not be received"):
        loader.ScanAhead(r).scan()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="Linux's parent-death signal")
def test_a_command_killed_outright_stops_its_child_with_a_checkpoint(scan_dir, tmp_path):
    out = tmp_path / "out"
    p, child = _training(scan_dir, out)
    try:
        p.kill()  # SIGKILL: the command can pass nothing on
        p.communicate(timeout=60)
    finally:
        p.kill()
    assert _gone(child, 120)  # it got SIGTERM and stopped as on any SIGTERM
    assert (out / "train" / "checkpoint.pt").exists() and not (out / "depth.npy").exists()
