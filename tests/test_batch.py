"""Many scans in one command (slwarp.batch): finding the scans, sharing them out, the summary, and a batch of
three small scans (one broken) under torchrun's two gloo processes on the CPU, resumed with worker processes."""
import json
import math
import os
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from slwarp.batch import (BatchSummary, ScanResult, find_scans, largest_first, scan_cost, shard, unique_names,
                          worker_cores)
from slwarp.cli import main as cli_main
from slwarp.scans.scan import ScanError


def fake_scan(folder: Path, marker: str = "scan.yaml", text: str = "units: mm\n") -> Path:
    """A folder that discovery takes for a scan (discovery never loads it)."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / marker).write_text(text)
    return folder


@pytest.fixture
def station(tmp_path):
    """day1/{bunny, vase (NeSS layout)}, day2/{bunny, chessboard (procam layout), notes (no scan)}, empty/."""
    fake_scan(tmp_path / "day1" / "bunny")
    fake_scan(tmp_path / "day1" / "vase", "config.ini", "[RawCalib]\n")
    fake_scan(tmp_path / "day2" / "bunny")
    fake_scan(tmp_path / "day2" / "chessboard", "calibration_result.xml", "<opencv_storage/>\n")
    (tmp_path / "day2" / "notes").mkdir()
    (tmp_path / "empty").mkdir()
    return tmp_path


def names_and_sources(found):
    return [(e.name, e.source.relative_to(e.source.parents[1]).as_posix()) for e in found.scans]


def test_find_scans_folders_of_scans_paths_and_globs(station, monkeypatch):
    monkeypatch.chdir(station)
    # a lone scan folder (or its scan.yaml): outputs straight into --out
    for spec in ("day1/bunny", "day1/bunny/scan.yaml", str(station / "day1" / "bunny")):
        found = find_scans([spec])
        assert found.single and names_and_sources(found) == [("bunny", "day1/bunny")], spec
    # a folder of scans: its scan subfolders, any layout, sorted; a subfolder without a scan is passed over
    found = find_scans(["day2"])
    assert not found.single and names_and_sources(found) == [("bunny", "day2/bunny"), ("chessboard", "day2/chessboard")]
    assert found.ignored == [Path("day2/notes")]
    # two folders: the two bunnies take their parent's name in front
    found = find_scans(["day1", "day2"])
    assert names_and_sources(found) == [("chessboard", "day2/chessboard"), ("day1-bunny", "day1/bunny"),
                                        ("day2-bunny", "day2/bunny"), ("vase", "day1/vase")]
    # globs: matches that are scans, folders of scans, or scan.yaml files; a scan named twice is one scan
    assert names_and_sources(find_scans(["day*/bunny"])) == [("day1-bunny", "day1/bunny"), ("day2-bunny", "day2/bunny")]
    assert names_and_sources(find_scans(["**/scan.yaml", "day1/bunny"])) == [("day1-bunny", "day1/bunny"),
                                                                            ("day2-bunny", "day2/bunny")]
    found = find_scans(["day?"])
    assert len(found.scans) == 4 and found.ignored == [Path("day2/notes")]
    assert not find_scans(["day1/b*"]).single  # a glob names a set, even of one scan


def test_find_scans_refuses_words_that_name_no_scan(station, monkeypatch):
    monkeypatch.chdir(station)
    cases = [(["day1", "nowhere"], "scan not found: nowhere"), (["empty"], "empty: holds no scan"),
             (["day2/notes"], "day2/notes: holds no scan"), (["day3*"], "day3*: no scan matches"),
             (["day1/bunny/scan.yaml/x"], "scan not found"), ([], "no scan given")]
    (station / "a_file.txt").write_text("x")
    cases.append((["a_file.txt"], "a_file.txt: not a scan folder"))
    for specs, message in cases:
        with pytest.raises(ScanError, match=message.replace("*", r"\*").replace("?", r"\?")):
            find_scans(specs)


def test_unique_names():
    assert unique_names([Path("/s/bunny"), Path("/s/vase")]) == ["bunny", "vase"]
    assert unique_names([Path("/d1/x/bunny"), Path("/d2/x/bunny"), Path("/d1/vase")]) == ["d1-x-bunny", "d2-x-bunny", "vase"]
    # a grown name that meets another folder's own name: that one grows too, if it can
    assert unique_names([Path("/x/c"), Path("/y/c"), Path("/z/x-c")]) == ["x-c", "y-c", "z-x-c"]
    # names still equal with every parent in front get a number, in the given order
    assert unique_names([Path("/x/c"), Path("/y/c"), Path("/x-c")]) == ["x-c", "y-c", "x-c-2"]


def test_sharding_is_longest_first_to_the_least_loaded_worker():
    # costs 5 3 3 2 2 1 over two workers, by hand: 5 -> w0 (5); 3 -> w1 (3); 3 -> w1 (6); 2 -> w0 (7); 2 -> w1 (8);
    # 1 -> w0 (8)
    assert shard([5, 3, 3, 2, 2, 1], 2) == [[0, 3, 5], [1, 2, 4]]
    assert shard([2, 2, 2, 2, 2], 2) == [[0, 2, 4], [1, 3]]  # equal costs deal round-robin
    assert shard([1, 9, 4], 5) == [[1], [2], [0], [], []]  # more workers than scans
    # an unknown cost counts as the mean of the known ones: (3 + 1 + 5 + 2) / 4 = 2.75
    assert largest_first([3, None, 1, 5, 2]) == [3, 0, 1, 4, 2]
    assert shard([3, None, 1, 5, 2], 2) == [[3, 4], [0, 1, 2]]
    assert shard([None, None, None], 2) == [[0, 2], [1]]
    with pytest.raises(ValueError, match="n_workers"):
        shard([1.0], 0)


def test_worker_cores_are_disjoint_contiguous_shares_of_the_allowed_cores():
    allowed = {0, 1, 2, 3, 4, 5, 6, 8, 9, 10}  # a launcher's affinity need not be 0..N-1
    shares = [worker_cores(i, 3, allowed) for i in range(3)]
    assert shares == [[0, 1, 2], [3, 4, 5], [6, 8, 9, 10]]
    assert worker_cores(4, 3, allowed) == shares[1]  # index taken modulo the count
    assert worker_cores(0, 1, allowed) == sorted(allowed)
    assert worker_cores(1, 4, {0, 1}) == [0, 1]  # fewer cores than workers: no pinning


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="no CPU affinity on this OS")
def test_a_worker_process_is_pinned_to_its_share_of_the_cores():
    """In a process of its own (pinning would bind the test runner): worker 1 of 2 keeps the second share."""
    allowed = sorted(os.sched_getaffinity(0))
    code = ("import os, torch; from slwarp.batch.launch import _enter_worker; _enter_worker('cpu', 1, 2); "
            "print(sorted(os.sched_getaffinity(0)), torch.get_num_threads())")
    env = {k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True).stdout
    share = worker_cores(1, 2, allowed)
    assert out.split("]")[0] + "]" == str(share)
    assert int(out.split("]")[1]) == len(share)


def test_scan_cost_is_pixels_times_frames_from_scan_yaml(tmp_path):
    frames = "".join(f"  - {{name: f{i}, image: images/{i}.png, pattern: patterns/{i}.png}}\n" for i in range(3))
    fake_scan(tmp_path / "a", text=f"camera: {{width: 320, height: 256}}\nframes:\n{frames}")
    assert scan_cost(tmp_path / "a") == 320 * 256 * 3
    assert scan_cost(fake_scan(tmp_path / "b", text="camera: [oops\n")) is None  # the scan reports it when it runs
    assert scan_cost(fake_scan(tmp_path / "c", "config.ini")) is None


def test_summary_totals_report_and_json(tmp_path):
    rows = [ScanResult("a", "/s/a", "/o/a", "done", "rank 0", "cpu", seconds=30.0, iterations=10, valid_share=0.5,
                       mae=1.0, completeness=0.9),
            ScanResult("b", "/s/b", "/o/b", "skipped", seconds=50.0, valid_share=0.75, mae=3.0, completeness=0.7),
            ScanResult("c", "/s/c", "/o/c", "done", "rank 1", "cpu", seconds=20.0, valid_share=0.0, mae=math.nan,
                       completeness=0.0),
            ScanResult("d", "/s/d", "/o/d", "failed", "rank 1", "cpu", seconds=0.5, error="ScanError: bad", traceback="tb")]
    summary = BatchSummary(rows, "torchrun", 2, wall_s=40.0, devices=["cpu", "cpu"])
    t = summary.totals()
    assert (t["scans"], t["done"], t["skipped"], t["failed"]) == (4, 2, 1, 1)
    assert t["scans_per_hour"] == pytest.approx(2 / 40.0 * 3600.0)  # scans reconstructed now per hour of wall time
    assert t["scan_s"] == pytest.approx(50.0)
    # no valid depth (c): no MAE, but its completeness of 0 counts: (0.9 + 0.7 + 0) / 3
    assert t["with_ground_truth"] == 2 and t["mean_mae"] == pytest.approx(2.0)
    assert t["mean_completeness"] == pytest.approx(1.6 / 3)
    report = summary.report()
    assert "failed: d (/s/d): ScanError: bad" in report and "180.0 scans/h" in report
    assert [line.split("|")[1].strip() for line in report.splitlines()[2:6]] == ["a", "b", "c", "d"]
    json_path, md_path = summary.write(tmp_path)
    doc = json.loads(json_path.read_text())  # strict JSON: NaN is written as null
    assert doc["scans"][2]["mae"] is None and doc["scans"][3]["traceback"] == "tb" and doc["totals"]["done"] == 2
    assert md_path.read_text().strip() == report


def test_cli_refuses_bad_batch_commands(tmp_path, capsys, monkeypatch):
    fake_scan(tmp_path / "s" / "a")
    base = ["reconstruct", "--out", str(tmp_path / "o"), "--device", "cpu", "--preset", "tiny"]
    assert cli_main(base + [str(tmp_path / "s"), str(tmp_path / "typo")]) == 2  # before any scan runs
    assert "scan not found" in capsys.readouterr().err and not (tmp_path / "o").exists()
    with pytest.raises(SystemExit):
        cli_main(base + [str(tmp_path / "s"), "--per-device", "-1"])
    assert "it takes an integer >= 0" in capsys.readouterr().err
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("RANK", "0")
    assert cli_main(base + [str(tmp_path / "s"), "--per-device", "2"]) == 2
    assert "--nproc-per-node" in capsys.readouterr().err


def test_visible_device_count_without_torch(monkeypatch):
    """The device count the command line starts its workers for, read without torch: CUDA_VISIBLE_DEVICES up
    to its first invalid entry, one for the CPU or a named GPU."""
    from slwarp.batch import visible_device_count

    assert visible_device_count("cpu") == 1 and visible_device_count("cuda:3") == 1
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "2,0,1")
    assert visible_device_count("cuda") == 3 and visible_device_count("auto") == 3
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "1,-1,0")
    assert visible_device_count("cuda") == 1
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "")
    assert visible_device_count("auto") == 1 and visible_device_count("cuda") is None  # no GPU: the CPU / an error


def test_workers_and_torchrun_ranks_see_only_their_gpu(monkeypatch):
    """The GPUs dealt out before any worker starts CUDA: worker w gets entry w % GPUs of CUDA_VISIBLE_DEVICES and
    keeps the launcher's name for it; a worker beyond per_device x GPUs is idle; without a GPU listing, nothing is
    dealt. A torchrun rank pins itself by LOCAL_RANK, and its rows name the GPU as the launcher numbered it."""
    from slwarp.batch import launch

    monkeypatch.setattr(launch, "_PINNED", None)
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "3,5")
    assert launch.visible_device_ids("auto") == ["3", "5"] and launch.visible_device_ids("cuda:1") == ["5"]
    assert launch.visible_device_ids("cuda:2") is None and launch.visible_device_ids("cpu") is None
    assert launch._worker_slots("cuda", 5, 2) == [("3", "cuda:0", 4), ("5", "cuda:1", 4), ("3", "cuda:0", 4),
                                                  ("5", "cuda:1", 4), "idle"]
    assert launch._worker_slots("cuda:1", 2, 2) == [("5", "cuda:1", 2), ("5", "cuda:1", 2)]
    assert launch._worker_slots("cpu", 2, 1) == [None, None] and launch._worker_slots(None, 1, 1) == [None]
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "")
    assert launch._worker_slots("auto", 2, 1) == [None, None]

    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "3,5")
    launch.pin_torchrun_rank("auto")  # not under torchrun: nothing
    assert os.environ["CUDA_VISIBLE_DEVICES"] == "3,5" and launch.device_label("cuda:0") == "cuda:0"
    for name, value in (("WORLD_SIZE", "2"), ("RANK", "1"), ("LOCAL_RANK", "1")):
        monkeypatch.setenv(name, value)
    launch.pin_torchrun_rank("cpu")  # a CPU run: nothing
    assert os.environ["CUDA_VISIBLE_DEVICES"] == "3,5"
    launch.pin_torchrun_rank("auto")
    assert os.environ["CUDA_VISIBLE_DEVICES"] == "5"
    assert launch.device_label("cuda:0") == "cuda:1" and launch.device_label("cpu") == "cpu"


# A batch end to end: the 'tiny' preset cut to a few iterations, on the torch twin with sphere-traced depth so that
# the worker processes compile no Warp kernel (the numbers do not matter here, only that each scan runs where the
# plan says and its outputs and summary line come back).
FAST = ["--preset", "tiny", "--device", "cpu", "--iters", "5", "--init", "sphere", "--rays", "128", "--mc-resolution", "32",
        "--backend", "torch", "--depth-method", "sphere", "--quiet"]


def test_batch_under_torchrun_with_a_broken_scan_then_resumed(tmp_path):
    from slwarp.batch import BatchOptions, run_batch
    from slwarp.neural.config import preset
    from slwarp.sim.simulate import simulate_scene

    scan = simulate_scene("spheres", "random6", rig="small")
    for name in ("a", "b", "broken"):
        scan.save(tmp_path / "scans" / name)
    missing = tmp_path / "scans" / "broken" / "images" / f"002_{scan.names[2]}.png"
    missing.unlink()
    out = tmp_path / "out"

    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    run = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--nproc-per-node", "2", "-m", "slwarp",
                          "reconstruct", "scans", "--out", "out", *FAST], cwd=tmp_path, env=env, capture_output=True,
                         text=True, timeout=300)
    assert run.returncode != 0, run.stdout + run.stderr  # a scan failed: rank 0 exits with 1, torchrun says so
    # every rank ends by its status alone (torchrun's own report of the failed status is not a rank's crash)
    assert not re.search(r"\[rank\d+\]: Traceback", run.stdout + run.stderr), run.stdout + run.stderr
    assert run.stdout.count("3 scans: 2 done, 0 skipped (complete before), 1 failed; torchrun, 2 worker(s)") == 1, run.stdout
    doc = json.loads((out / "summary.json").read_text())
    rows = {r["name"]: r for r in doc["scans"]}
    assert list(rows) == ["a", "b", "broken"] and doc["mode"] == "torchrun" and doc["devices"] == ["cpu", "cpu"]
    # the plan: equal costs (320 x 256 x 6 each) deal round-robin in name order
    assert {k: r["worker"] for k, r in rows.items()} == {"a": "rank 0", "b": "rank 1", "broken": "rank 0"}
    for name in ("a", "b"):
        r = rows[name]
        assert r["status"] == "done" and r["iterations"] == 5 and r["error"] is None, r
        assert 0 < r["valid_share"] <= 1 and r["mae"] is not None and 0 < r["completeness"] <= 1
        assert (r["frames"], r["pixels"]) == (6, 320 * 256)
        for f in ("depth.npy", "depth.png", "config.yaml", "timings.json", "metrics.json"):
            assert (out / name / f).is_file(), (name, f)
    # the same scan and config give the same result in either process
    assert (rows["a"]["mae"], rows["a"]["valid_share"]) == (rows["b"]["mae"], rows["b"]["valid_share"])
    bad = rows["broken"]
    assert bad["status"] == "failed" and bad["error"].startswith("ScanError:") and str(missing) in bad["error"]
    assert "Traceback" in bad["traceback"] and not (out / "broken" / "depth.npy").exists()
    assert f"failed: broken ({tmp_path / 'scans' / 'broken'}): ScanError" in (out / "summary.md").read_text()

    # resumed with worker processes started here (two per device, one needed): the finished scans are skipped with
    # their numbers, the broken one is tried again and fails alone
    found = find_scans([tmp_path / "scans"])
    cfg = preset("tiny", device="cpu", iters=5, init="sphere", rays=128, mc_resolution=32, backend="torch",
                 depth_method="sphere")
    summary = run_batch(found.scans, cfg, out, BatchOptions(resume=True, log=False), per_device=2)
    rows2 = {r.name: r for r in summary.results}
    assert [rows2[k].status for k in ("a", "b", "broken")] == ["skipped", "skipped", "failed"]
    assert summary.mode == "per-device" and summary.workers == 1 and rows2["broken"].worker == "worker 0"
    assert str(missing) in rows2["broken"].error
    for name in ("a", "b"):
        assert rows2[name].mae == pytest.approx(rows[name]["mae"]) and rows2[name].valid_share == pytest.approx(
            rows[name]["valid_share"])
    assert json.loads((out / "summary.json").read_text())["totals"]["skipped"] == 2


def test_per_device_workers_start_before_the_command_imports_torch(tmp_path):
    """`reconstruct SCANS --per-device 2` as a user runs it: its two workers are started before the command's
    own imports (their first marks come before its 'imports' mark), share the three scans, the broken one fails
    alone, and the summary holds all three."""
    from slwarp.sim.simulate import simulate_scene

    scan = simulate_scene("spheres", "random6", rig="small")
    for name in ("a", "b", "broken"):
        scan.save(tmp_path / "scans" / name)
    (tmp_path / "scans" / "broken" / "images" / f"002_{scan.names[2]}.png").unlink()
    marks = tmp_path / "timeline.jsonl"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "SLWARP_TIMELINE": str(marks)}
    run = subprocess.run([sys.executable, "-m", "slwarp", "reconstruct", "scans", "--out", "out", "--per-device", "2",
                          *FAST], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 1, run.stdout + run.stderr  # a scan failed
    doc = json.loads((tmp_path / "out" / "summary.json").read_text())
    rows = {r["name"]: r for r in doc["scans"]}
    assert doc["mode"] == "per-device" and doc["workers"] == 2 and list(rows) == ["a", "b", "broken"]
    assert [rows[k]["status"] for k in ("a", "b", "broken")] == ["done", "done", "failed"]
    assert {r["worker"] for r in rows.values()} <= {"worker 0", "worker 1"}
    assert rows["a"]["mae"] == pytest.approx(rows["b"]["mae"])
    assert all((tmp_path / "out" / k / "config.yaml").is_file() for k in ("a", "b"))
    lines = [json.loads(line) for line in marks.read_text().splitlines()]
    parent = next(doc for doc in lines if any(name == "imports" for name, _ in doc["marks"]))
    imports = dict(parent["marks"])["imports"]
    workers = [dict(doc["marks"]) for doc in lines if doc["pid"] != parent["pid"]]
    assert len(workers) == 2 and all(w["worker started"] < imports for w in workers), lines


def test_per_device_with_a_missing_scan_starts_no_worker(tmp_path):
    """A --per-device command that will fail on its scans starts no worker: the error comes as without it."""
    marks = tmp_path / "timeline.jsonl"
    env = {**os.environ, "SLWARP_TIMELINE": str(marks)}
    run = subprocess.run([sys.executable, "-m", "slwarp", "reconstruct", str(tmp_path / "typo"), "--out", "out",
                          "--per-device", "2", *FAST], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert run.returncode == 2 and "scan not found" in run.stderr, run.stderr
    lines = [json.loads(line) for line in marks.read_text().splitlines()]
    assert len(lines) == 1 and not any(name.startswith("pool") for name, _ in lines[0]["marks"]), lines


def test_workers_beyond_per_device_take_nothing(tmp_path):
    """A pool started for more devices than torch sees (the count read without torch was wrong): the workers
    beyond per_device x the devices end without a scan, the others do every scan, and `active` counts them."""
    from slwarp.batch import BatchOptions, ScanJob, WorkerPool
    from slwarp.batch.launch import _Fixed
    from slwarp.neural.config import preset
    from slwarp.sim.simulate import simulate_scene

    scan = simulate_scene("spheres", "random6", rig="small")
    for name in ("a", "b"):
        scan.save(tmp_path / "scans" / name)
    cfg = preset("tiny", device="cpu", iters=5, init="sphere", rays=128, mc_resolution=32, backend="torch",
                 depth_method="sphere")
    jobs = [ScanJob(n, str(tmp_path / "scans" / n), str(tmp_path / "out" / n), 1.0) for n in ("a", "b")]
    pool = WorkerPool(3, _Fixed(cfg), BatchOptions(log=False), per_device=1)  # one device: the CPU
    rows = pool.run(jobs)
    assert [r.status for r in rows] == ["done", "done"] and {r.worker for r in rows} == {"worker 0"}
    assert pool.active == 1 and all(p.exitcode == 0 for p in pool._procs)


def test_a_worker_that_dies_fails_the_scans_it_held_and_no_other(tmp_path):
    """A WorkerPool whose only worker is killed during its first scan: that scan and the one it had drawn ahead
    (being loaded) are failed with the worker's exit code, the scan it never took is 'not run', and run() returns."""
    import signal as signals

    from slwarp.batch import BatchOptions, ScanJob, WorkerPool
    from slwarp.neural.config import preset
    from slwarp.sim.simulate import simulate_scene

    scan = simulate_scene("spheres", "random6", rig="small")
    for name in ("a", "b", "c"):
        scan.save(tmp_path / "scans" / name)
    cfg = preset("tiny", device="cpu", iters=2000, init="sphere", rays=128, mc_resolution=32, backend="torch",
                 depth_method="sphere")
    from slwarp.batch.launch import _Fixed

    jobs = [ScanJob(n, str(tmp_path / "scans" / n), str(tmp_path / "out" / n), 1.0) for n in ("a", "b", "c")]
    pool = WorkerPool(1, _Fixed(cfg), BatchOptions(log=False))
    staging = tmp_path / "out" / f".a.partial-{pool._procs[0].pid}"  # reconstruct('a') has begun

    def kill_when_training():
        t = time.monotonic()
        while not staging.exists() and time.monotonic() - t < 120:
            time.sleep(0.05)
        time.sleep(0.5)  # 'b' is drawn once 'a' is in memory
        os.kill(pool._procs[0].pid, signals.SIGKILL)

    killer = threading.Thread(target=kill_when_training)
    killer.start()
    rows = pool.run(jobs)
    killer.join()
    assert [r.status for r in rows] == ["failed", "failed", "failed"], rows
    assert all("the worker process ended (exit code -9) during this scan" == r.error for r in rows[:2]), rows
    assert rows[2].error == "not run: every worker process ended before it"
    assert not (tmp_path / "out" / "a" / "depth.npy").exists()


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_batch_over_two_nodes_with_a_broken_scan(tmp_path):
    """Two torchrun launchers on this machine as two nodes (c10d rendezvous), one process each, writing into one
    output folder: every good scan is done once, by one of the two ranks, the broken one fails alone, and rank 0's
    summary holds all four; both launchers exit 1 (a scan failed) without waiting on each other."""
    from slwarp.sim.simulate import simulate_scene

    scan = simulate_scene("spheres", "random6", rig="small")
    for name in ("a", "b", "c", "broken"):
        scan.save(tmp_path / "scans" / name)
    missing = tmp_path / "scans" / "broken" / "images" / f"002_{scan.names[2]}.png"
    missing.unlink()
    endpoint = f"127.0.0.1:{_free_port()}"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    launch = [sys.executable, "-m", "torch.distributed.run", "--nnodes", "2", "--nproc-per-node", "1",
              "--rdzv-backend", "c10d", "--rdzv-endpoint", endpoint, "--rdzv-id", "two-nodes", "-m", "slwarp",
              "reconstruct", "scans", "--out", "out", *[a for a in FAST if a != "--quiet"]]  # per-scan lines
    nodes = [subprocess.Popen(launch, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                              text=True) for _ in range(2)]
    logs = [n.communicate(timeout=300)[0] for n in nodes]
    assert [n.returncode for n in nodes] == [1, 1], logs
    assert not any(re.search(r"\[rank\d+\]: Traceback", log) for log in logs), logs  # a status, not a rank's crash
    doc = json.loads((tmp_path / "out" / "summary.json").read_text())
    rows = {r["name"]: r for r in doc["scans"]}
    assert list(rows) == ["a", "b", "broken", "c"] and doc["mode"] == "torchrun" and doc["workers"] == 2
    assert {r["worker"] for r in rows.values()} == {"rank 0", "rank 1"}
    for name in ("a", "b", "c"):
        assert rows[name]["status"] == "done" and (tmp_path / "out" / name / "depth.npy").is_file(), rows[name]
    assert rows["broken"]["status"] == "failed" and str(missing) in rows["broken"]["error"]
    assert doc["totals"]["done"] == 3 and doc["totals"]["failed"] == 1
    report = "".join(logs)
    assert report.count("4 scans: 3 done, 0 skipped (complete before), 1 failed; torchrun, 2 worker(s)") == 1, report
    for name in ("a", "b", "c"):  # each good scan reconstructed once: one start line (rank, device) per scan
        assert len(re.findall(rf"\] {name}: done in", report)) == 1, report


def test_compiled_graphs_are_kept_for_scans_of_the_same_sizes(monkeypatch):
    """A batch keeps torch.compile's graphs from scan to scan while the image size, frame count and settings stay
    (the working volume reaches them as tensors) and drops them at a scan of other sizes or settings (dynamo's
    recompile limit)."""
    import types

    import torch._dynamo

    from slwarp.batch import jobs as batch

    resets = []
    monkeypatch.setattr(torch._dynamo, "reset", lambda: resets.append(1))
    monkeypatch.setattr(batch, "_compiled_for", None)

    class Scan:
        def __init__(self, h, w, n):
            self.camera, self.n = types.SimpleNamespace(height=h, width=w), n

        def __len__(self):
            return self.n

    from slwarp.neural.config import preset

    fast, other = preset("fast"), preset("fast", rays=512)
    for s, cfg, expected in ((Scan(1024, 1280, 6), fast, 0), (Scan(1024, 1280, 6), fast, 0),
                             (Scan(1024, 1280, 9), fast, 1), (Scan(800, 1280, 9), fast, 2),
                             (Scan(800, 1280, 9), fast, 2), (Scan(800, 1280, 9), other, 3)):
        batch._fit_compiled(s, cfg)
        assert len(resets) == expected


def test_batches_on_gpus_run_two_scans_a_gpu_by_default(tmp_path, monkeypatch):
    """Without --per-device, several scans on GPUs (told without torch) of DEFAULT_PER_GPU_MIN_GIB or more run
    DEFAULT_PER_GPU at a time on each; one after another in this process on the CPU, for one scan folder, under
    torchrun, on smaller GPUs or where the GPUs or their memory cannot be told; --per-device K as given, 0 for one after
    another."""
    import argparse

    from slwarp.batch import launch
    from slwarp.cli import neural
    from slwarp import driver

    fake_scan(tmp_path / "s" / "a")
    fake_scan(tmp_path / "s" / "b")
    monkeypatch.delenv("WORLD_SIZE", raising=False)
    monkeypatch.delenv("RANK", raising=False)
    gpus, memory = [["0", "1"]], [80.0]
    monkeypatch.setattr(launch, "visible_device_ids", lambda device: gpus[0] if device != "cpu" else None)
    monkeypatch.setattr(driver, "smallest_gpu_memory_gib", lambda: memory[0])

    def per_device(scans, given=None, device=None):
        args = argparse.Namespace(scans=[str(s) for s in scans], per_device=given, device=device, config=None)
        return neural._per_device(args, neural._found_or_none(args))

    batch = [tmp_path / "s"]
    assert neural.DEFAULT_PER_GPU == 2 and per_device(batch) == 2 and per_device(batch, device="cuda") == 2
    assert per_device(batch, given=3) == 3 and per_device(batch, given=0) is None
    assert per_device(batch, device="cpu") is None
    assert per_device([tmp_path / "s" / "a"]) is None  # one scan folder
    assert per_device([tmp_path / "s" / "a", tmp_path / "missing"]) is None  # the command reports it
    memory[0] = neural.DEFAULT_PER_GPU_MIN_GIB - 1
    assert per_device(batch) is None
    memory[0] = None
    assert per_device(batch) is None
    memory[0], gpus[0] = 80.0, None
    assert per_device(batch) is None
    gpus[0] = ["MIG-4f1c2a3b-0000-0000-0000-000000000000"]  # a slice of a GPU: NVML's total is the whole GPU's
    assert per_device(batch) is None
    gpus[0] = ["0"]
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("RANK", "0")
    assert per_device(batch) is None


def test_smallest_gpu_memory_without_a_driver_is_unknown(monkeypatch):
    """No NVML library (this machine, or any without NVIDIA's driver): None, so the batch keeps one process."""
    import ctypes

    from slwarp import driver

    def missing(name, *a, **k):
        raise OSError(f"{name}: cannot open shared object file")

    monkeypatch.setattr(ctypes, "CDLL", missing)
    assert driver.smallest_gpu_memory_gib() is None
