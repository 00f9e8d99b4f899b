"""bench/residual_speed.py on the small rig: every way of computing the residual agrees with the dense one, the
growth gives the same map with sparse and dense confidences, the grouping's sizes are consistent, and the table and JSON are written."""
import importlib.util
import json
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "bench"


def test_residual_speed_bench_checks_and_writes(tmp_path):
    spec = importlib.util.spec_from_file_location("residual_speed", BENCH / "residual_speed.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    assert bench.main(["--rig", "small", "--scene", "bunny", "--repeat", "1", "--out", str(tmp_path)]) == 0
    doc = json.loads((tmp_path / "residual-speed-cpu.json").read_text())
    assert [r["share"] for r in doc["residual"]] == list(bench.SHARES)
    assert all(r["same"] for r in doc["residual"]) and doc["growth"]["same"]
    assert all("sparse_s" in r for r in doc["residual"] if r["share"] < 1.0)
    assert 0 < doc["growth"]["grown"] <= doc["growth"]["patch_pixels"]
    assert doc["median3"]["same"] and doc["grouping"]["same"] and 0 < doc["grouping"]["groups"] < doc["grouping"]["pixels"]
    assert "| share of pixels with depth |" in (tmp_path / "residual-speed-cpu.md").read_text()
