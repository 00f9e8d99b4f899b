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
    assert "| 1 | empty |" in (tmp_path / "command-wall-cpu-tiny.md").read_text()
    # --scan: a scan on disk instead of the simulated one (here the one the run above simulated)
    scan = tmp_path / "work" / "scan-spheres-small"
    command_wall.main(["--smoke", "--runs", "1", "--scan", str(scan), "--work", str(tmp_path / "work2"),
                       "--out", str(tmp_path), "--stem", "on-disk"])
    doc = json.loads((tmp_path / "on-disk.json").read_text())
    assert doc["setup"]["scan"] == str(scan) and str(scan) in doc["command"] and "error" not in doc["runs"][0]
    assert not (tmp_path / "work2" / "scan-spheres-small").exists()  # nothing simulated
    with pytest.raises(SystemExit, match="no such scan folder"):
        command_wall.main(["--smoke", "--scan", str(tmp_path / "missing"), "--work", str(tmp_path / "w3"),
                           "--out", str(tmp_path)])


def test_options_become_the_commands_flags():
    assert command_wall.option_flags(["iters=3", "compile=false", "cuda_graph=true", "field=hashgrid"]) == [
        "--iters", "3", "--no-compile", "--cuda-graph", "--field", "hashgrid"]
