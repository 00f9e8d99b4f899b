"""bench/real_captures.py without data or a GPU: what a run's timings say about the refinement, and the tables."""
from bench import real_captures


def test_refinement_facts_read_the_extraction_timings():
    assert real_captures.refinement_facts({"refined": False, "refine_misfit": 0.0264, "refine_check": None}) == \
        {"refined": False, "refine_misfit": 0.0264, "refine_kept": None, "lens_halo": None}
    kept = real_captures.refinement_facts({"refined": True, "refine_misfit": None,
                                           "refine_check": {"keep": True, "before": [0.04], "after": [0.03]},
                                           "pattern_halo": 0.11})
    assert kept == {"refined": True, "refine_misfit": None, "refine_kept": True, "lens_halo": 0.11}
    assert real_captures.refinement_facts({}) == {"refined": None, "refine_misfit": None, "refine_kept": None,
                                                  "lens_halo": None}

def _row(capture, method, rms, **extra):
    return {"capture": capture, "method": method, "plane_rms_mm": rms, "quadric_rms_mm": rms / 2,
            "plate_coverage": 0.5, "agree_median_mm": 0.3, "agree_over_2mm": 0.1, "pixels_with_depth": 0.7, **extra}

def test_tables_give_the_means_and_the_refinement_decisions():
    rows = [_row(0, "full 40-image gc-interp", 0.6, model_misfit=0.0264),
            _row(0, "GC(7)-interp, same 7 images", 2.0),
            _row(0, "fast", 0.7, wall_s=20.0, depth_map_s=12.0, refined=False, refine_misfit=0.027, refine_kept=None),
            _row(1, "full 40-image gc-interp", 0.2, model_misfit=0.0321),
            _row(1, "GC(7)-interp, same 7 images", 0.6),
            _row(1, "fast", 0.5, wall_s=21.0, depth_map_s=13.0, refined=True, refine_misfit=None, refine_kept=True)]
    doc = {"date": "2026-11-26", "device": "Test GPU", "command": "python -m bench.real_captures run --presets fast",
           "depth_range_mm": [800.0, 2600.0], "frames": real_captures.SEVEN_ROWS, "rows": rows}
    md = real_captures.markdown(doc, [0, 1], ["full 40-image gc-interp", "GC(7)-interp, same 7 images", "fast"])
    plate = {line.split("|")[1].strip(): [c.strip() for c in line.strip("|").split("|")[1:]]
             for line in md.splitlines() if line.startswith("| ") and line.count("|") == 5}
    assert plate["fast"] == ["0.700", "0.500", "0.600"]
    assert plate["GC(7)-interp, same 7 images"][-1] == "1.300"
    lines = md.splitlines()
    assert any(line.startswith("| 0 | fast |") and line.endswith("| no (misfit 0.0270) |") for line in lines)
    assert any(line.startswith("| 1 | fast |") and line.endswith("| yes (check kept) |") for line in lines)
    assert any(line.startswith("| 1 | full 40-image gc-interp |") and "(0.0321 at this depth)" in line for line in lines)


def test_an_extraction_variant_continues_its_presets_checkpoint_and_does_not_train_again(tmp_path):
    import json

    import torch

    from slwarp.neural.config import preset, save_config
    from slwarp.neural.training.checkpoint import read_checkpoint
    from slwarp.sim.simulate import SimOptions, simulate_scene

    folder = tmp_path / "scan"
    simulate_scene("spheres", "random6", rig="small", options=SimOptions(seed=3)).save(folder)
    opts = {"iters": 20, "init": "sphere", "init_iters": 10, "rays": 64, "mc_resolution": 32}
    save_config(tmp_path / "base.yaml", preset("tiny", device="cpu", **opts))
    save_config(tmp_path / "variant.yaml", preset("tiny", device="cpu", **opts, doubt_confidence=0.8))
    base = {"label": "tiny", "capture": 0, "scan": folder, "config": tmp_path / "base.yaml", "out": tmp_path / "base",
            "depth_range": None}
    done = real_captures._run_one(base, None)
    assert done["rc"] == 0, done.get("tail")
    variant = dict(base, label="tiny+doubt_confidence=0.8", config=tmp_path / "variant.yaml", out=tmp_path / "variant",
                   base_out=base["out"])
    done = real_captures._run_one(variant, None)
    assert done["rc"] == 0, done.get("tail")
    base_ck = read_checkpoint(base["out"] / "train" / "checkpoint.pt")
    variant_ck = read_checkpoint(variant["out"] / "train" / "checkpoint.pt")
    assert variant_ck["iteration"] == base_ck["iteration"]
    for name, tensor in base_ck["field"].items():  # the same field, not a new training
        assert torch.equal(tensor, variant_ck["field"][name])
    # no training step ran in the variant's process: its training time is what the base run's checkpoint carried
    timings = {k: json.loads((job["out"] / "timings.json").read_text()) for k, job in (("base", base), ("v", variant))}
    assert timings["v"]["iterations"] == timings["base"]["iterations"] == 20
    assert timings["v"]["train_s"] < 0.25 * timings["base"]["train_s"]
    assert "doubt_confidence: 0.8" in (variant["out"] / "config.yaml").read_text()
    assert (base["out"] / "train" / "checkpoint.pt").is_file()  # the preset's own run is left as it was


def test_the_coverage_counts_the_full_decodes_pixels_given_a_depth_within_2_mm():
    import numpy as np

    from slwarp.scans.scanner import Camera

    full = np.full((4, 5), np.nan, np.float32)
    full[:2] = 1500.0  # 10 pixels of the full decode
    depth = np.full_like(full, np.nan)
    depth[0] = 1501.5  # 5 within 2 mm
    depth[1, :2] = 1505.0  # 2 off by 5 mm
    depth[1, 2] = 1498.0  # 1 at exactly 2 mm
    depth[3] = 1400.0  # 5 where the full decode has none: not counted
    region = np.zeros(full.shape, bool)
    region[0] = True
    cam = Camera(5, 4, [[1000.0, 0, 2.0], [0, 1000.0, 1.5], [0, 0, 1]])
    m = real_captures.capture_metrics(depth, {"full_decode": full, "region": region}, cam)
    assert m["agree_coverage"] == 0.6
    rows = [_row(0, "fast", 0.5, agree_coverage=m["agree_coverage"]), _row(0, "GC(7)-interp, same 7 images", 2.0,
                                                                           agree_coverage=0.55)]
    doc = {"date": "2026-11-29", "device": "Test GPU", "command": "c", "depth_range_mm": [800.0, 2600.0],
           "frames": real_captures.SEVEN_ROWS, "rows": rows}
    md = real_captures.markdown(doc, [0], ["GC(7)-interp, same 7 images", "fast"]).splitlines()
    at = md.index("## The full decode's pixels with a depth within 2 mm of it")
    assert md[at + 4] == "| GC(7)-interp, same 7 images | 55.0% | 55.0% |"
    assert md[at + 5] == "| fast | 60.0% | 60.0% |"
