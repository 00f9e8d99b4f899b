"""bench/batch_throughput.py without running anything: the per-stage means of a configuration's scans and their
table."""
import json
from pathlib import Path

import pytest

from bench import batch_throughput


def _scan(folder: Path, name: str, seconds: float, setup: float, train: float, depth_map: float, total: float) -> dict:
    out = folder / name
    out.mkdir(parents=True)
    (out / "timings.json").write_text(json.dumps({"setup_s": setup, "train_s": train, "depth_map_s": depth_map,
                                                  "total_s": total, "iterations": 10}))
    return {"name": name, "out_dir": str(out), "status": "done", "seconds": seconds, "worker": "rank 0"}


def test_stage_means_split_each_scan_into_setup_train_extract_and_other(tmp_path):
    done = [_scan(tmp_path, "a", 10.0, 1.0, 4.0, 7.0, 7.5), _scan(tmp_path, "b", 6.0, 0.5, 2.0, 4.5, 5.0)]
    done.append({"name": "c", "out_dir": str(tmp_path / "missing"), "status": "done", "seconds": 99.0})  # no timings
    means = batch_throughput.stage_means(done)
    assert means == pytest.approx({"setup": 0.75, "train": 3.0, "extract": 2.0, "other": 1.75})
    assert batch_throughput.stage_means(done[2:]) is None
    doc = {"device": "CPU", "date": "2026-11-25", "gpus": 0, "bench_command": "x",
           "setup": {"cpu": True, "scans": 2, "rig": "small", "patterns": "random6", "scenes": ["spheres"],
                     "preset": "tiny", "set": [], "smoke": False, "compile_cache": "warm"},
           "configs": [{"name": "1cpu", "gpus": 1, "per_gpu": 1, "launcher": "sequential", "completed": 2, "done": 2,
                        "failed": 0, "timed_out": False, "returncode": 0, "wall_s": 20.0, "scans_per_hour": 360.0,
                        "stages": means, "command": "slwarp reconstruct ..."}]}
    md = batch_throughput.markdown(doc)
    assert "| 1cpu | 0.75 | 3.00 | 2.00 | 1.75 |" in md
    assert "filled by the warm-up and shared" in md


def test_set_options_reach_the_command_as_its_flags():
    from bench.batch_throughput import reconstruct_flags

    assert reconstruct_flags("fast", "cuda", ["compile=true", "iters=20"]) == [
        "--preset", "fast", "--device", "cuda", "--compile", "--iters", "20"]
    assert reconstruct_flags("fast", "cpu", ["compile=false"])[-1] == "--no-compile"


def test_each_launcher_gives_its_command(tmp_path):
    """1x1 runs the scans one after another in one process (`--per-device 0`: the command's own default on GPUs is
    two a GPU), GxK:per-device passes K, Gx1:plain is the command as typed, with no launcher flag."""
    from bench.batch_throughput import command, parse_config

    def flags(token):
        cmd = command(parse_config(token, "gpu"), tmp_path / "scans", tmp_path / "out", ["--preset", "fast"])
        return cmd[cmd.index("--preset"):]

    assert flags("1x1") == ["--preset", "fast", "--per-device", "0"]
    assert flags("4x2:per-device") == ["--preset", "fast", "--per-device", "2"]
    assert flags("4x1:plain") == ["--preset", "fast"] and parse_config("4x1:plain", "gpu")["name"] == "4gpu-plain"
    with pytest.raises(SystemExit, match="plain"):
        parse_config("1x2:plain", "gpu")
