"""bench/train_speed.py runs on the CPU with tiny sizes (a smoke test of the hash-grid configs, the twin
encoding and the end-to-end rows; its figures are not checked: timings are never asserted)."""
import importlib.util
import json
import math
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench" / "train_speed.py"


def load_bench():
    spec = importlib.util.spec_from_file_location("train_speed", BENCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_train_speed_smoke_hashgrid_on_cpu(tmp_path):
    bench = load_bench()
    bench.main(["--preset", "tiny", "--scene", "spheres", "--rig", "small", "--warmup", "1", "--iters", "2",
                "--configs", "warp:eager:fp32", "warp:eager:fp32:twin", "--end-to-end", "--backends", "warp",
                "--set", "field=hashgrid", "grid_levels=4", "grid_log2_table=10", "iters=3", "init_iters=2",
                "mc_resolution=16", "--out", str(tmp_path)])
    doc = json.loads((tmp_path / "train-speed-cpu-tiny.json").read_text())
    assert [r["config"] for r in doc["rows"]] == ["warp:eager:fp32", "warp:eager:fp32:twin"]
    assert all(r["field"] == "hashgrid" and math.isfinite(r["ms_per_it"]) for r in doc["rows"])
    (e2e,) = doc["end_to_end"]
    assert e2e["field"] == "hashgrid" and e2e["timings"]["iterations"] == 5 and e2e["warmup_s"] > 0
    md = (tmp_path / "train-speed-cpu-tiny.md").read_text()
    assert "warp:eager:fp32:twin / warp:eager:fp32" in md and "with field=hashgrid" in md


def test_train_speed_rejects_bad_specs():
    bench = load_bench()
    with pytest.raises(SystemExit, match="BACKEND:MODE:MATMUL"):
        bench.parse_spec("warp:eager:fp32:twins")
    assert bench.parse_spec("torch:compile:tf32:graph:twin") == {
        "options": dict(backend="torch", compile=True, matmul="tf32", cuda_graph=True), "twin": True}
