"""bench/model_misfit.py on one small-rig scene: the linear camera under the refinement limit, a gamma-2.2 camera
over it, both written to the JSON and the table; an unknown camera model is refused by name."""
import json

import pytest

from bench import model_misfit


def test_model_misfit_bench_writes_the_survey(tmp_path):
    assert model_misfit.main(["--rigs", "small", "--scenes", "spheres", "--cameras", "linear,gamma",
                              "--camera-rigs", "small", "--no-real", "--out", str(tmp_path)]) == 0
    doc = json.loads((tmp_path / "model-misfit-cpu.json").read_text())
    lin, gam = doc["scans"]["linear"]["small"]["spheres"], doc["scans"]["gamma"]["small"]["spheres"]
    assert lin < doc["limit"] < gam
    md = (tmp_path / "model-misfit-cpu.md").read_text()
    assert f"{lin:.4f}" in md and "linear 0 of 1; gamma 1 of 1" in md


def test_model_misfit_bench_refuses_an_unknown_camera(tmp_path):
    with pytest.raises(SystemExit, match="unknown camera model 'fisheye'"):
        model_misfit.main(["--cameras", "linear,fisheye", "--no-real", "--out", str(tmp_path)])
