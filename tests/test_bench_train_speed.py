"""bench/train_speed.py runs on the CPU with tiny sizes (a smoke test of the hash-grid configs, the twin
encoding and the end-to-end rows; its figures are not checked: timings are never asserted)."""
import json
import math

import pytest

from bench import train_speed


def load_bench():
    return train_speed


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
    # the timed steps carry the preset's own start (the depth-search map and the terms that use it)
    assert all(r["init"] == "search" for r in doc["rows"])
    # time per step along the run, from the logged iterations (the last is logged in any case)
    assert e2e["timeline"][-1]["to"] == 5 and all(x["ms_per_it"] > 0 and x["inv_s"] > 0 for x in e2e["timeline"])
    md = (tmp_path / "train-speed-cpu-tiny.md").read_text()
    assert "warp:eager:fp32:twin / warp:eager:fp32" in md and "with field=hashgrid" in md
    assert doc["bench_command"].startswith("python -m bench.train_speed --preset tiny") and "`python -m bench" in md


def test_train_speed_times_a_trained_field(tmp_path):
    """--init trained runs the preset's whole schedule before the timed steps (the state the run's own steps see)."""
    bench = load_bench()
    bench.main(["--preset", "tiny", "--scene", "spheres", "--rig", "small", "--warmup", "1", "--iters", "2",
                "--configs", "warp:eager:fp32", "--init", "trained", "--set", "field=hashgrid", "grid_levels=4",
                "grid_log2_table=10", "iters=3", "init_iters=2", "--out", str(tmp_path)])
    (row,) = json.loads((tmp_path / "train-speed-cpu-tiny.json").read_text())["rows"]
    assert row["init"] == "search, trained" and row["trained_iters"] == 5  # 3 + the 2 of the warm-up
    assert math.isfinite(row["ms_per_it"]) and row["warmup_s"] > 0


def test_train_speed_rejects_bad_specs():
    bench = load_bench()
    with pytest.raises(SystemExit, match="BACKEND:MODE:MATMUL"):
        bench.parse_spec("warp:eager:fp32:twins")
    assert bench.parse_spec("torch:compile:tf32:graph:twin") == {
        "options": dict(backend="torch", compile=True, matmul="tf32", cuda_graph=True), "twin": True}


def test_kernel_labels_and_table():
    bench = load_bench()
    assert bench.kernel_label("encode_backward_9a8b7c6d_cuda_kernel_forward") == "warp:encode_backward"
    assert bench.kernel_label("render_kernels_cuda_kernel_forward") == "warp:render_kernels"
    long = "void at::native::vectorized_elementwise_kernel<4, at::native::FillFunctor<float>>(int)" * 2
    assert len(bench.kernel_label(long)) == 70 and bench.kernel_label(long).endswith("...")
    row = {"config": "warp:compile:tf32:graph", "ms_per_it": 2.0, "it_per_s": 500.0, "projected_s": 8.0,
           "iters_of_preset": 4000, "graph_used": True,
           "breakdown_ms": {"kernels": [{"kernel": "warp:encode_backward", "ms": 0.912, "launches": 1.0},
                                        {"kernel": "a|b", "ms": 0.1, "launches": 3.0}]}}
    doc = {"device": "GPU", "date": "d", "preset": "accurate", "options": [], "scene": "bunny", "rig": "default",
           "warmup": 1, "iters": 2, "rows": [row], "end_to_end": []}
    md = bench.markdown(doc)
    assert "| warp:encode_backward | 0.912 | 1 |" in md and "| a/b | 0.100 | 3 |" in md
