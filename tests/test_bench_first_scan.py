"""bench/first_scan.py: a fresh process on the CPU with tiny settings (a smoke test; timings are never asserted),
and its table with a failed run."""
import json

import pytest

from bench import first_scan


def test_first_scan_smoke_on_cpu(tmp_path):
    first_scan.main(["--smoke", "--runs", "1", "--fresh", "--work", str(tmp_path / "work"), "--out", str(tmp_path)])
    doc = json.loads((tmp_path / "first-scan-cpu-tiny.json").read_text())
    (run,) = doc["runs"]
    assert "error" not in run and run["caches"] == "empty"
    first, second = run["scans"]
    assert run["process_wall_s"] > run["to_first_depth_map_s"] > first["depth_map_s"] > 0
    assert abs(first["setup_s"] + first["train_s"] + first["extract_s"] - first["depth_map_s"]) < 1e-6
    assert first["mae"] is not None and second["mae"] is not None  # the simulated scan has ground truth
    assert (tmp_path / "work" / "scan-spheres-small" / "scan.yaml").is_file()
    md = (tmp_path / "first-scan-cpu-tiny.md").read_text()
    assert "| 1 | empty |" in md
    # each part of both scans side by side: the set-up's phases, the first step, the extraction's stages
    assert {"step 1", "extract: marching_cubes", "extract: depth"} <= set(first["parts"]) == set(second["parts"])
    assert any(k.startswith("setup: ") for k in first["parts"])
    assert "| part | first scan | second scan | first - second |" in md and "| extract: " in md
    # --scan: a scan on disk (here the one simulated above), nothing simulated; a missing folder is refused
    scan = tmp_path / "work" / "scan-spheres-small"
    first_scan.main(["--smoke", "--runs", "1", "--scan", str(scan), "--work", str(tmp_path / "work2"), "--out",
                     str(tmp_path), "--stem", "on-disk"])
    doc = json.loads((tmp_path / "on-disk.json").read_text())
    assert doc["setup"]["scan"] == str(scan) and "error" not in doc["runs"][0]
    assert not (tmp_path / "work2" / "scan-spheres-small").exists()
    with pytest.raises(SystemExit, match="no such scan folder"):
        first_scan.main(["--smoke", "--scan", str(tmp_path / "missing"), "--work", str(tmp_path / "w3")])


def test_first_scan_table_reports_a_failed_run():
    scan = {"setup_s": 1.0, "train_s": 2.0, "extract_s": 0.5, "depth_map_s": 3.5}
    doc = {"device": "CPU", "date": "2026-11-26", "bench_command": "python bench/first_scan.py",
           "setup": {"preset": "tiny", "scene": "spheres", "rig": "small", "set": [], "fresh": True, "smoke": False},
           "runs": [{"caches": "empty", "process_wall_s": 9.0, "imports_s": 2.0, "device_start_s": 0.5, "load_s": 0.1,
                     "to_first_depth_map_s": 6.0, "scans": [scan, {**scan, "depth_map_s": 1.5}]},
                    {"caches": "warm", "process_wall_s": 1.0, "error": "Traceback ...\nRuntimeError: out of memory"}]}
    md = first_scan.markdown(doc)
    assert "| 1 | empty | 9.0 | 2.00 | 0.50 | 6.00 | 1.00 / 2.00 / 0.50 | 1.00 / 2.00 / 0.50 | 3.50 / 1.50 | 2.00 |" in md
    assert "| 2 | warm | 1.0 | failed: Traceback ... / RuntimeError: out of memory |" in md
    assert "emptied before run 1" in md
