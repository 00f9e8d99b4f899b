"""bench/command_wall.py: the reconstruct command as a fresh process on the CPU with tiny settings (a smoke test;
timings are never asserted, only that the phases account for the command's wall time), and the option flags."""
import json

import pytest

from bench import command_wall


def test_command_wall_smoke_on_cpu(tmp_path):
    command_wall.main(["--smoke", "--runs", "1", "--cold", "--work", str(tmp_path / "work"), "--out", str(tmp_path)])
    doc = json.loads((tmp_path / "command-wall-cpu-tiny.json").read_text())
    (run,) = doc["runs"]
    assert "error" not in run and run["caches"] == "empty" and run["rc"] == 0
    phases = sum(run[k] for k, _ in command_wall.PHASES)
    assert abs(phases - run["wall_s"]) < 1e-3  # the phases tile the time from spawn to exit
    assert 0 < run["to_depth_map"] < run["wall_s"]
    assert (tmp_path / "work" / "out-1" / "depth.npy").is_file()
    md = (tmp_path / "command-wall-cpu-tiny.md").read_text()
    assert "| 1 | empty |" in md
    # the host beside the runs: its CPU and its bare torch import, three fresh processes
    assert doc["host"]["cores"] >= 1 and len(doc["host"]["torch_import_s"]) == 3
    assert all(t > 0 for t in doc["host"]["torch_import_s"])
    assert '`python -c "import torch"` took' in md and doc["host"]["cpu"] in md
    # --scan: a scan on disk instead of the simulated one (here the one the run above simulated)
    scan = tmp_path / "work" / "scan-spheres-small"
    command_wall.main(["--smoke", "--runs", "1", "--scan", str(scan), "--work", str(tmp_path / "work2"),
                       "--out", str(tmp_path), "--stem", "on-disk", "--host-imports", "0"])
    doc = json.loads((tmp_path / "on-disk.json").read_text())
    assert doc["host"] is None and "import torch" not in (tmp_path / "on-disk.md").read_text()
    assert doc["setup"]["scan"] == str(scan) and str(scan) in doc["command"] and "error" not in doc["runs"][0]
    assert not (tmp_path / "work2" / "scan-spheres-small").exists()  # nothing simulated
    with pytest.raises(SystemExit, match="no such scan folder"):
        command_wall.main(["--smoke", "--scan", str(tmp_path / "missing"), "--work", str(tmp_path / "w3"),
                           "--out", str(tmp_path)])


def test_options_become_the_commands_flags():
    assert command_wall.option_flags(["iters=3", "compile=false", "cuda_graph=true", "field=hashgrid"]) == [
        "--iters", "3", "--no-compile", "--cuda-graph", "--field", "hashgrid"]


def test_sampled_runs_say_where_the_main_thread_was(tmp_path):
    """--sample: the forked child's samples found and reported per phase; the places' seconds fit in their phase."""
    command_wall.main(["--smoke", "--runs", "1", "--sample", "--work", str(tmp_path / "work"), "--out", str(tmp_path),
                       "--stem", "sampled"])
    (run,) = json.loads((tmp_path / "sampled.json").read_text())["runs"]
    rep = run["sampled"]
    phases = {p["phase"]: p for p in rep["phases"]}
    assert {"interpreter and imports", "setup", "training", "extraction"} <= set(phases)
    for p in rep["phases"]:
        assert sum(s for _, s in p["places"]) <= p["seconds"] + 0.05
    assert phases["setup"]["places"] and any("slwarp/" in place for place, _ in phases["setup"]["places"])
    assert all(g["ms"] >= 25 for g in rep["gaps"])
    assert "## Where the main thread was" in (tmp_path / "sampled.md").read_text()


def test_sampler_report_gives_each_interval_to_its_phase():
    from bench import stack_sampler

    marks = {"started": 0.0, "imports": 1.0, "scan loaded": 1.1, "reconstruct": 1.2, "reconstructed": 3.0, "exit": 3.1}
    timings = {"setup_s": 0.5, "train_s": 1.0, "depth_map_s": 1.7}
    stack = ["site-packages/torch/x.py:f:1", "slwarp/neural/a.py:g:2", "bench/stack_sampler.py:run:3"]
    samples = [(t / 100, stack) for t in range(0, 300)] + [(3.05, stack)]
    samples.insert(150, (1.495, stack))  # 1.49 -> 1.495 -> 1.50, and a lock held from 2.99 to 3.05
    rep = stack_sampler.report(samples, marks, timings)
    got = {p["phase"]: p for p in rep["phases"]}
    assert got["setup"]["seconds"] == 0.5 and got["setup"]["places"][0][0] == "slwarp/neural/a.py:g < x.py:f:1"
    assert abs(got["training"]["places"][0][1] - 1.0) < 0.02
    assert [g["ms"] for g in rep["gaps"]] == [60.0] and rep["gaps"][0]["phase"] == "metrics, outputs"
