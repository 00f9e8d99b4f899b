"""bench/watch_station.py: `slwarp watch` over scans already in its inbox, as a fresh process on the CPU with tiny
settings (a smoke test: timings are never asserted, only that every scan's line is found and timed in order)."""
import json

from bench import watch_station


def test_watch_station_smoke_on_cpu(tmp_path):
    watch_station.main(["--smoke", "--runs", "1", "--work", str(tmp_path / "work"), "--out", str(tmp_path)])
    doc = json.loads((tmp_path / "watch-station-cpu-tiny.json").read_text())
    (run,) = doc["runs"]
    assert run["rc"] == 0 and run["scans_done"] == 3, run["lines"]
    assert 0 < run["first_scan_s"] < run["wall_s"] and len(run["gaps_s"]) == 2 and all(g >= 0 for g in run["gaps_s"])
    assert abs(run["later_scan_s"] - sum(run["gaps_s"]) / 2) < 1e-9
    for name in ("00-bunny", "01-vase", "02-spheres"):
        assert (tmp_path / "work" / "out-1" / name / "depth.npy").is_file(), name
    md = (tmp_path / "watch-station-cpu-tiny.md").read_text()
    assert "| 1 |" in md and "00-bunny:" in md
