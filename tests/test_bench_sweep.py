"""bench/accuracy_sweep.py without running anything: --report writes the tables (means, targets, where the missing
pixels went) from the finished runs in --state, --also-extract variants included; runs that do not match the
command's jobs are not taken."""
import json
from pathlib import Path

import pytest

from bench import accuracy_sweep

SCENES = ("bunny", "rods")


def _metrics(mae, complete, **extra):
    return {"mae": mae, "median": mae / 2, "over_5mm": 0.001, "completeness": complete, "mae_within_5mm": mae / 2,
            "outlier_mae": mae / 2, **extra}


def _state(folder: Path, stale: bool = False):
    folder.mkdir()
    for i, scene in enumerate(SCENES):
        job = {"kind": "neural", "label": "tiny", "preset": "tiny", "overrides": {}, "rig": "default", "scene": scene,
               "seed": 0, "also_extract": ["search_doubt=true"]}
        if stale:
            job["also_extract"] = []  # another command's run: not this sweep's job
        lost = {"unlit": 0.03, "flying_pixel": 0.01, "low_confidence": 0.02}
        methods = {"tiny": _metrics(0.4 + i, 0.95, lost=lost, train_s=10.0, total_s=12.0),
                   "tiny+search_doubt=true": _metrics(0.2 + i, 0.94, lost={**lost, "search_doubt": 0.01})}
        (folder / f"{accuracy_sweep.job_key(job)}.json").write_text(json.dumps({"job": job, "methods": methods}))
        cjob = {"kind": "classical", "rig": "default", "scene": scene, "seed": 0}
        (folder / f"{accuracy_sweep.job_key(cjob)}.json").write_text(json.dumps(
            {"job": cjob, "methods": {"GC(7) interp": _metrics(1.0, 0.97), "GC(6) interp": _metrics(2.0, 0.96)}}))


def _report(tmp_path, state, *extra):
    return accuracy_sweep.main(["--report", "--device-name", "Test GPU", "--presets", "tiny", "--also-extract",
                                "search_doubt=true", "--rigs", "default", "--scenes", ",".join(SCENES), "--state",
                                str(state), "--out", str(tmp_path / "out"), "--stem", "sweep", *extra])


def test_report_writes_the_tables_of_finished_runs(tmp_path):
    _state(tmp_path / "state")
    assert _report(tmp_path, tmp_path / "state", "--note", "runs made on two machines") == 0
    doc = json.loads((tmp_path / "out" / "sweep.json").read_text())
    means = {lab: d["mean"]["mae"] for lab, d in doc["table"]["default"].items()}
    assert means["tiny"] == pytest.approx(0.9) and means["tiny+search_doubt=true"] == pytest.approx(0.7)
    assert doc["table"]["default"]["tiny+search_doubt=true"]["targets"]["mae_over_gc7"] == pytest.approx(0.7)
    md = (tmp_path / "out" / "sweep.md").read_text()
    assert "Test GPU" in md and "the tables of the finished runs" in md
    # the note is said once, as prose after the command, not again inside it
    assert md.count("runs made on two machines") == 1 and "--note" not in md and "--stem sweep`" in md
    lost = md[md.index("Where the missing pixels went"):]
    cells = next([c.strip() for c in line.strip("|").split("|")] for line in lost.splitlines()
                 if line.startswith("| tiny+search_doubt=true "))
    # unlit, no surface, out of range, flying pixel, low confidence, search doubt: % of the mask
    assert cells[1:] == ["3.00", "0.00", "0.00", "1.00", "2.00", "1.00"]


def test_report_ignores_runs_of_other_jobs(tmp_path):
    _state(tmp_path / "state", stale=True)
    assert _report(tmp_path, tmp_path / "state") == 0
    doc = json.loads((tmp_path / "out" / "sweep.json").read_text())
    assert "tiny" not in doc["table"]["default"]
    assert "mean" in doc["table"]["default"]["GC(7) interp"]


def test_keep_writes_the_error_picture_and_the_signed_error_and_fates(tmp_path, monkeypatch):
    """--keep: <job>__<method>.png and .npz with the signed error (float16, NaN outside the mask or without depth)
    and the pixel fates with their names."""
    import numpy as np
    from types import SimpleNamespace

    from slwarp.neural.extraction import FATE, PIXEL_FATES

    monkeypatch.setattr(accuracy_sweep, "_KEEP", str(tmp_path))
    gt = np.full((6, 8), 700.0, np.float32)
    mask = np.ones_like(gt, bool)
    mask[0] = False
    depth = gt + 0.25
    depth[1, :2] = np.nan
    fate = np.full(gt.shape, FATE["measured"], np.uint8)
    fate[1, :2] = FATE["low_confidence"]
    job = {"kind": "neural", "label": "tuned", "rig": "default", "scene": "rods", "seed": 0}
    accuracy_sweep.keep_error_map(job, "tuned+uniform_fill=true", depth, SimpleNamespace(gt_depth=gt, mask=mask), fate)
    stem = tmp_path / "tuned__default__rods__s0__tuned+uniform_fill-true"
    assert stem.with_suffix(".png").is_file()
    z = np.load(stem.with_suffix(".npz"))
    err = z["error"]
    assert err.dtype == np.float16 and np.isnan(err[0]).all() and np.isnan(err[1, :2]).all()
    np.testing.assert_allclose(err[2:], 0.25, atol=1e-3)
    np.testing.assert_array_equal(z["fate"], fate)
    assert tuple(z["fates"]) == PIXEL_FATES


def test_gray7_runs_train_on_the_seven_gray_code_images_and_are_kept_apart(tmp_path):
    """--neural-frames gray7: the neural runs select the 7 most significant Gray code images along the depth axis
    (what GC(7) decodes and the real captures give), their state files do not collide with the random-pattern runs,
    and a gray7 report does not take random6 runs."""
    from slwarp.sim.rigs import rig_name

    scan, axis = accuracy_sweep._scan(rig_name("vertical", True), "bunny", 0)
    job = {"kind": "neural", "label": "tiny", "preset": "tiny", "overrides": {}, "rig": "vertical_small",
           "scene": "bunny", "seed": 0, "frames": "gray7"}
    chosen = scan.select(accuracy_sweep.neural_frames(job, axis))
    assert axis == "row" and len(chosen) == 7
    assert [r.bit for r in chosen.roles] == list(range(7)) and all(r.axis == "row" and not r.inverse for r in chosen.roles)
    assert all(n.startswith("rand") for n in scan.select(accuracy_sweep.neural_frames({}, axis)).names)
    assert accuracy_sweep.job_key(job) != accuracy_sweep.job_key({**job, "frames": None})

    _state(tmp_path / "state")  # random-pattern runs only
    assert _report(tmp_path, tmp_path / "state", "--neural-frames", "gray7") == 0
    doc = json.loads((tmp_path / "out" / "sweep.json").read_text())
    assert "tiny" not in doc["table"]["default"] and doc["neural_frames"] == "gray7"
    assert "7 most significant Gray code images" in (tmp_path / "out" / "sweep.md").read_text()


def test_job_key_names_the_camera_model_when_it_is_not_the_linear_one():
    """--camera: runs through another camera model are other runs in --state (their own key), linear ones keep the
    keys of the tables made before the option."""
    job = {"kind": "neural", "label": "fast", "rig": "default", "scene": "bunny", "seed": 0}
    assert accuracy_sweep.job_key(job) == "fast__default__bunny__s0"
    assert accuracy_sweep.job_key({**job, "camera": "linear"}) == "fast__default__bunny__s0"
    assert accuracy_sweep.job_key({**job, "camera": "halo"}) == "fast__halo__default__bunny__s0"


def _spawned(pid: int) -> set[int]:
    """The pids of a process's children that multiprocessing spawned to run work (Linux /proc): its pool's workers and
    its Manager's server, not its resource tracker (which ends on its own once its pipe closes)."""
    found = set()
    for task in Path(f"/proc/{pid}/task").iterdir():
        for child in (task / "children").read_text().split():
            try:
                if "spawn_main" in Path(f"/proc/{child}/cmdline").read_text():
                    found.add(int(child))
            except FileNotFoundError:  # ended meanwhile
                pass
    return found


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="reads the children from Linux's /proc")
def test_sigterm_stops_the_workers_and_keeps_what_finished(tmp_path):
    """A sweep sent SIGTERM while its workers train ends within seconds with status 130, its worker processes gone
    (not left training after it), and says where its finished runs are."""
    import os
    import signal
    import subprocess
    import sys
    import time

    cmd = [sys.executable, "-m", "bench.accuracy_sweep", "--small", "--presets", "tiny", "--set", "iters=5000",
           "--rigs", "default", "--scenes", "bunny", "--workers", "2", "--out", str(tmp_path)]
    proc = subprocess.Popen(cmd, cwd=accuracy_sweep.REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.time() + 120
        workers = set()
        while time.time() < deadline and len(workers) < 3:  # the Manager's server and the two workers
            time.sleep(0.5)
            workers = _spawned(proc.pid)
        assert len(workers) >= 3, "the sweep started no workers"
        time.sleep(5)  # the workers are importing or training
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130
    assert "interrupted" in err and str(tmp_path / "accuracy-state") in err
    time.sleep(1)
    alive = []
    for pid in workers:
        try:
            os.kill(pid, 0)
            alive.append(pid)
        except ProcessLookupError:
            pass
    assert not alive, f"worker processes still running after the sweep ended: {alive}"


def test_max_minutes_keeps_the_runs_under_way(tmp_path):
    """--max-minutes stops starting runs once a run finishes after it; the runs under way then finish and are kept in
    the state folder like every other (each printed run has its file), and the runs not started are not."""
    import subprocess
    import sys

    cmd = [sys.executable, "-m", "bench.accuracy_sweep", "--small", "--presets", "tiny", "--set", "iters=20,init_iters=10",
           "--rigs", "default", "--workers", "2", "--max-minutes", "0.0001", "--out", str(tmp_path)]
    res = subprocess.run(cmd, cwd=accuracy_sweep.REPO, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "--max-minutes 0.0001 reached" in res.stdout
    printed = [line.split()[1] for line in res.stdout.splitlines() if line.startswith("[")]
    saved = sorted(f.stem for f in (tmp_path / "accuracy-state").glob("*.json"))
    assert sorted(printed) == saved
    assert 2 <= len(saved) < 16, saved  # the run beside the first one finished too; most of the 16 never started
