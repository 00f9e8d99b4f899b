"""bench/first_scan.py: a fresh process on the CPU with tiny settings (a smoke test; timings are never asserted),
and its table with a failed run."""
import json

import pytest

from bench import first_scan


def test_first_scan_smoke_on_cpu(tmp_path):
    first_scan.main(["--smoke", "--runs", "1", "--fresh", "--ops", "--work", str(tmp_path / "work"), "--out",
                     str(tmp_path)])
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
    # --ops: each torch op's first call per scan, named by the pipeline's function that made it
    use = run["first_use"]
    assert use["distinct_ops"][0] > 20 and use["distinct_ops"][0] == use["distinct_ops"][1]
    wheres = {w for w, _, _ in use["by_where"]}
    assert "slwarp/neural/start/search.py:search_depth" in wheres
    assert all(w == "?" or w.split("/")[0] in ("slwarp", "kernels") for w in wheres)
    assert "| where | first scan ms | second scan ms | first - second |" in md and "The costliest first calls" in md
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


def test_op_summary_orders_functions_by_the_first_scans_excess():
    first = {"ops": [{"op": "aten.sort", "dtypes": "float32", "ms": 30.0, "at": "slwarp/a.py:f"},
                     {"op": "aten.add", "dtypes": "float32", "ms": 5.0, "at": "slwarp/b.py:g"},
                     {"op": "aten.add", "dtypes": "float64", "ms": 1.0, "at": "slwarp/a.py:f"}],
             "warp_loads": [{"module": "m", "ms": 4.0}]}
    second = {"ops": [{"op": "aten.sort", "dtypes": "float32", "ms": 0.5, "at": "slwarp/a.py:f"},
                      {"op": "aten.add", "dtypes": "float32", "ms": 0.1, "at": "slwarp/c.py:h"}], "warp_loads": []}
    u = first_scan.op_summary(first, second, top=2)
    assert u["by_where"] == [["slwarp/a.py:f", 31.0, 0.5], ["slwarp/b.py:g", 5.0, 0.0], ["slwarp/c.py:h", 0.0, 0.1]]
    assert [(r["op"], r["second_ms"]) for r in u["costliest"]] == [("aten.sort", 0.5), ("aten.add", 0.1)]
    assert u["ops_ms"] == [36.0, 0.6] and u["distinct_ops"] == [3, 2] and u["warp_loads_ms"] == [4.0, 0.0]
    md = first_scan.first_use_tables([{"caches": "warm", "first_use": u}])
    assert "| slwarp/a.py:f | 31.0 | 0.5 | +30.5 |" in md and "| slwarp/c.py:h |" not in "\n".join(md)
