"""The scanning station (slwarp.watch): when a folder counts as a complete scan, settling, and `slwarp watch` end
to end on the CPU: two scans dropped into the inbox, a broken one beside them, both good ones reconstructed once,
Ctrl-C (SIGINT) leaving every finished scan complete; a restart skips them."""
import os
import shutil
import signal
import subprocess
import sys
import threading
import time

import pytest

from slwarp.batch import ScanJob, outputs_complete
from slwarp.watch import Station, Watcher, scan_complete

# the `tiny` preset cut to a few iterations, on the torch twin with sphere-traced depth (no Warp kernel to compile
# in the child process); the numbers do not matter here
FAST = ["--preset", "tiny", "--device", "cpu", "--iters", "5", "--init", "sphere", "--rays", "128", "--mc-resolution", "32",
        "--backend", "torch", "--depth-method", "sphere"]


@pytest.fixture(scope="module")
def small_scan(tmp_path_factory):
    from slwarp.sim.simulate import simulate_scene

    folder = tmp_path_factory.mktemp("scan") / "spheres"
    simulate_scene("spheres", "random6", rig="small").save(folder)
    return folder


def test_a_scan_is_complete_once_its_yaml_and_every_file_it_names_are_there(small_scan, tmp_path):
    folder = tmp_path / "s"
    folder.mkdir()
    assert scan_complete(folder) == (False, "no scan file yet")
    (folder / "scan.yaml").write_text("camera: {width: 3")  # a half-written scan.yaml
    assert not scan_complete(folder)[0]
    shutil.copy(small_scan / "scan.yaml", folder / "scan.yaml")
    ok, why = scan_complete(folder)
    assert not ok and "missing" in why
    shutil.copytree(small_scan, folder, dirs_exist_ok=True)
    assert scan_complete(folder) == (True, "")
    (folder / "calibration_result.xml").write_text("<opencv_storage/>")  # other layouts: the marker file
    other = tmp_path / "procam"
    other.mkdir()
    (other / "calibration_result.xml").write_text("<opencv_storage/>")
    assert scan_complete(other) == (True, "")


def test_a_folder_is_taken_only_after_it_settled_and_links_out_of_the_inbox_are_ignored(small_scan, tmp_path):
    inbox, out = tmp_path / "inbox", tmp_path / "out"
    inbox.mkdir()
    said = []
    w = Watcher(inbox, out, station=None, settle_s=1.0, say=said.append)
    shutil.copytree(small_scan, inbox / "a")
    assert w.ready(now=0.0) == []  # first seen: not settled yet
    assert w.ready(now=0.5) == []
    assert w.ready(now=1.5) == [inbox / "a"]
    (inbox / "a" / "notes.txt").write_text("still copying")  # a change starts the wait again
    assert w.ready(now=1.6) == [] and w.ready(now=2.0) == []
    assert w.ready(now=2.7) == [inbox / "a"]
    outside = tmp_path / "elsewhere"
    shutil.copytree(small_scan, outside)
    os.symlink(outside, inbox / "b", target_is_directory=True)
    assert w.ready(now=10.0) == [inbox / "a"] and w.ready(now=20.0) == [inbox / "a"]
    assert said == [f"b: ignored (a link leading out of {inbox})"]  # said once


def test_the_station_reconstructs_scan_after_scan_and_reports_a_broken_one(small_scan, tmp_path):
    from slwarp.neural.config import preset

    cfg = preset("tiny", device="cpu", iters=5, init="sphere", rays=128, mc_resolution=32, backend="torch",
                 depth_method="sphere")
    station = Station(cfg)
    row = station.reconstruct(small_scan, tmp_path / "a")
    assert row.status == "done" and outputs_complete(tmp_path / "a") and row.mae is not None
    broken = tmp_path / "broken"
    shutil.copytree(small_scan, broken)
    next(broken.glob("images/*.png")).unlink()
    bad = station.reconstruct(broken, tmp_path / "b")
    assert bad.status == "failed" and bad.error.startswith("ScanError:") and not (tmp_path / "b" / "depth.npy").exists()
    assert [r.status for r in station.results] == ["done", "failed"]
    # scan after scan: the next loads while one trains, each one's files are written while the next trains, and
    # on_row(row) comes once its files are complete, in order; should_stop ends the run before a scan starts
    reported = []
    jobs = [ScanJob(n, str(src), str(tmp_path / n)) for n, src in (("c", small_scan), ("d", broken), ("e", small_scan),
                                                                     ("f", small_scan))]
    asked = []  # should_stop is asked before each scan: stop before the fourth
    rows = station.run(iter(jobs), on_row=lambda r: reported.append((r.name, r.status, outputs_complete(r.out_dir))),
                       should_stop=lambda: asked.append(1) or len(asked) > 3)
    assert [r.name for r in rows] == ["c", "d", "e"] and [r.status for r in rows] == ["done", "failed", "done"]
    assert reported == [("c", "done", True), ("d", "failed", False), ("e", "done", True)]
    assert not (tmp_path / "f").exists() and [r.name for r in station.results[-3:]] == ["c", "d", "e"]


def _wait_for(predicate, timeout: float, what: str, proc, lines: list) -> None:
    t = time.monotonic()
    while not predicate():
        if proc.poll() is not None:
            raise AssertionError(f"the station ended early ({proc.returncode}) while waiting for {what}:\n"
                                 + "\n".join(lines))
        if time.monotonic() - t > timeout:
            raise AssertionError(f"timed out waiting for {what}:\n" + "\n".join(lines))
        time.sleep(0.2)


def test_slwarp_watch_end_to_end_then_ctrl_c(small_scan, tmp_path):
    inbox, out = tmp_path / "inbox", tmp_path / "out"
    inbox.mkdir()
    cmd = [sys.executable, "-u", "-m", "slwarp", "watch", str(inbox), "--out", str(out), "--poll", "0.2",
           "--settle", "0.5", *FAST]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(ln.rstrip("\n") for ln in proc.stdout), daemon=True)
    reader.start()
    try:
        # scans arrive as a scanner writes them: copied in (a temporary name, then renamed), one broken
        for name in ("a", "broken", "b"):
            shutil.copytree(small_scan, tmp_path / f".{name}")
            if name == "broken":  # complete (every file there) but an image is not a PNG
                next((tmp_path / f".{name}").glob("images/*.png")).write_bytes(b"not a png")
            os.rename(tmp_path / f".{name}", inbox / name)
        _wait_for(lambda: sum(ln.startswith(("a: ", "b: ", "broken: ")) for ln in lines) == 3, 300,
                  "three scan lines", proc, lines)
        assert outputs_complete(out / "a") and outputs_complete(out / "b")
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=60)
        reader.join(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
    text = "\n".join(lines)
    assert proc.returncode == 130, text
    lines = text.splitlines()
    assert any(ln.startswith("a: ") and " s, depth on " in ln and "MAE" in ln for ln in lines), text
    assert any(ln.startswith("b: ") and " s, depth on " in ln for ln in lines), text
    assert any(ln.startswith("broken: failed after") and "ScanError" in ln for ln in lines), text
    assert sum(ln.startswith("a: ") for ln in lines) == 1  # reconstructed once
    assert "stopped: 2 scan(s) reconstructed, 1 failed" in text
    for name in ("a", "b"):
        assert outputs_complete(out / name)

    # a restart takes nothing done again and stops when idle
    run = subprocess.run(cmd + ["--until-idle"], capture_output=True, text=True, env=env, timeout=120)
    assert run.returncode == 0, run.stdout + run.stderr
    assert "a: done before" in run.stdout and "b: done before" in run.stdout
    assert "broken: failed after" in run.stdout  # tried again once in a new process
    assert "stopped: 0 scan(s) reconstructed, 1 failed" in run.stdout
