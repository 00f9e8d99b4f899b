"""bench/grow_study.py grows a kept depth map again (a hand-made one on the small rig: a patch 40 mm behind its
surface inside a block of repaired pixels) and reports what the growth set right."""
import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench"


def load(name):
    spec = importlib.util.spec_from_file_location(name, BENCH / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_grow_study_on_a_kept_map(tmp_path):
    from slwarp.neural.pattern_model import lit_with_contrast, offset_and_modulation
    from slwarp.neural.extraction import FATE, PIXEL_FATES

    study = load("grow_study")
    sweep = load("accuracy_sweep")
    scan, _ = sweep._scan("small", "steps", 0)
    _, b = offset_and_modulation(scan.select("rand*").images)
    valid = lit_with_contrast(b) & scan.mask
    y0, x0 = next((y, x) for y in range(10, 200, 10) for x in range(10, 260, 10)
                  if valid[y : y + 30, x : x + 40].all() and np.ptp(scan.gt_depth[y : y + 30, x : x + 40]) < 15.0)
    error = np.where(valid, 0.0, np.nan)
    patch = (slice(y0 + 5, y0 + 25), slice(x0 + 30, x0 + 36))
    error[patch] = 40.0
    fate = np.where(valid, FATE["measured"], FATE["no_contrast"]).astype(np.uint8)
    fate[y0 : y0 + 30, x0 : x0 + 40] = FATE["repaired"]
    fate[patch] = FATE["measured"]
    keep = tmp_path / "keep"
    keep.mkdir()
    np.savez_compressed(keep / "tuned__small__steps__s0__tuned.npz", error=error.astype(np.float16), fate=fate,
                        fates=np.array(PIXEL_FATES))
    np.savez_compressed(keep / "classical__small__steps__s0__GC7interp.npz", error=error.astype(np.float16))
    assert study.main(["--keep", str(keep), "--supports", "3", "--out", str(tmp_path)]) == 0
    doc = json.loads((tmp_path / "grow-study.json").read_text())
    (run,) = doc["runs"]  # the classical run is not a growth's
    assert (run["rig"], run["scene"], run["seeds"]) == ("small", "steps", int((fate == FATE["repaired"]).sum()))
    g = run["supports"]["3"]
    assert g["grown"] >= 0.9 * 120 and g["right"] == g["grown"] and g["wrong"] == 0
    assert run["wrong_before"] == 120 and g["wrong_after"] <= 12 and g["mae_after"] < run["mae_before"]
    assert "| tuned small steps |" in (tmp_path / "grow-study.md").read_text()
    with pytest.raises(SystemExit, match="no neural run"):
        study.main(["--keep", str(keep), "--runs", "nothing*", "--out", str(tmp_path)])
