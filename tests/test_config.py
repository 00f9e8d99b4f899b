"""The typed configuration: presets, validation with clear messages, YAML in and out, flat option names, and
the CLI options generated from it."""
import dataclasses
import math
import subprocess
import sys
import warnings

import pytest

from slwarp import cli
from slwarp.neural.config import (OPTIONS, PRESET_SUMMARIES, PRESETS, SECTIONS, ConfigError, TrainConfig, load_config,
                                  parse_assignments, preset, save_config)

# The presets as flat fields, written out by hand from the flat TrainConfig they replace: the sections must
# hold exactly these values (a change here is a change of behaviour).
FLAT_DEFAULTS = dict(iters=4000, rays=2048, n_samples=32, n_importance=32, up_sample_steps=4, lr=1e-4, lr_decay="none",
                     lr_final=0.05, variance_lr_factor=1.0, lambda_rc=1.0, lambda_sc=1.0, sc_start=1000, lambda_reg=0.1, level_adam_steps=False, lens_variance_lr_factor=None, lens_lambda_reg=None, anneal_end=0,
                     contrast_threshold=0.05, pattern_blur="auto", pattern_halo=0.0, pattern_halo_sigma=40.0, doubt_rays=0.0, doubt_rays_radius=1, doubt_rays_until=1.0, confidence="photometric", min_confidence=0.6,
                     hidden=256, layers=8, skip=4,
                     n_freqs=6, init="search", init_iters=300, auto_range=False, auto_range_margin_mm=50.0, search_step_mm=1.0, search_stride=2, search_window_step=0, seed=0, backend="warp",
                     device="auto", matmul="fp32", compile=True, cuda_graph=True, incremental=False, start_frames=3,
                     add_every=500, checkpoint_every=500, log_every=50, retry_lost_surface=True, mc_resolution=384, depth_method="mesh",
                     edge_filter=10.0, edge_readmit=False, edge_readmit_support=3, edge_readmit_confidence=0.9, refine_range=0.0, search_repair=False, repair_min_component=0, repair_grow=False, search_doubt=False, doubt_confidence=0.7,
                     uniform_fill=False, step_split_radius=0, step_split_margin=0.9, edge_side_radius=0, edge_side_margin=0.5, refine_check=False, refine_through_halo=True, refine_max_misfit=0.0, denoise_radius=0, denoise_footprints=4.0, hole_fill=0, hole_fill_footprints=0.5, edge_band_radius=0, edge_band_confidence=0.8, edge_band_sides="both", edge_band_far_radius=0, edge_band_far_confidence=0.0, surface_weight=0.0, surface_after=0.0, surface_in_front=False, free_space=0.0, surface_band_mm=0.5,
                     field="mlp", grid_levels=16, grid_log2_table=19, grid_base=16, grid_finest="auto",
                     grid_hidden=64, grid_layers=1, grid_activation="softplus", grid_gradient="finite_difference",
                     grid_table_lr_factor=10.0, grid_start_levels=2, grid_level_every=150,
                     stages=("marching_cubes", "depth", "depth_range", "flying_pixel", "confidence"))
# the extraction stages of tuned, fast, accurate and cpu-hashgrid, in order
SEARCH_STAGES = (*FLAT_DEFAULTS["stages"], "search_repair", "refine", "uniform_fill", "repair_grow", "denoise")
# fast and accurate: the edge sides settled before the denoising
EDGE_SIDE_STAGES = (*SEARCH_STAGES[:-1], "edge_side", "denoise")
HOLE_FILL_STAGES = (*EDGE_SIDE_STAGES, "hole_fill")
# fast and accurate: the edge band last
EDGE_BAND_STAGES = (*HOLE_FILL_STAGES, "edge_band")
# fast and accurate: the ramps split before the edge sides are settled
STEP_SPLIT_STAGES = (*SEARCH_STAGES[:-1], "step_split", "edge_side", "denoise", "hole_fill", "edge_band")
HASHGRID = dict(field="hashgrid", lr=1e-3, lr_decay="cosine", lambda_sc=0.0, grid_table_lr_factor=10.0)
FLAT_PRESETS = {
    "paper": dict(matmul="tf32"),
    "tuned": dict(matmul="tf32", lr=5e-4, lr_decay="cosine", lambda_sc=0.0, refine_range=3.0, refine_max_misfit=0.024,
                  pattern_halo="auto", refine_through_halo=False,
                  edge_readmit=True,
                  search_doubt=True,
                  search_repair=True, repair_min_component=100, repair_grow=True, surface_weight=1.0, surface_after=1.0,
                  uniform_fill=True, denoise_radius=4, denoise_footprints=8.0, stages=SEARCH_STAGES),
    "cpu": dict(iters=1500, rays=384, n_samples=24, n_importance=16, up_sample_steps=2, lr=5e-4, lr_decay="cosine",
                lambda_sc=0.0, hidden=64, layers=4, skip=2, n_freqs=6, search_step_mm=2.0, mc_resolution=192,
                checkpoint_every=250, log_every=25),
    "tiny": dict(iters=300, rays=256, n_samples=16, n_importance=8, up_sample_steps=1, lr=5e-4, lr_decay="cosine",
                 sc_start=100, hidden=48, layers=3, skip=None, n_freqs=4, init_iters=100, search_step_mm=2.0,
                 search_stride=3, mc_resolution=128, checkpoint_every=100, log_every=25),
    "fast": dict(matmul="tf32", compile=False, iters=800, init_iters=200, rays=1024, up_sample_steps=2, grid_levels=8,
                 doubt_rays=0.5, doubt_rays_until=0.5,
                 grid_gradient="finite_difference_4",
                 grid_start_levels=2, grid_level_every=50, mc_resolution=256, checkpoint_every=1000, refine_range=3.0,
                 refine_max_misfit=0.024, search_doubt=True, search_repair=True, repair_min_component=100, repair_grow=True,
                 surface_weight=1.0, surface_after=1.0, surface_in_front=True, free_space=0.5, variance_lr_factor=4.0, uniform_fill=True, denoise_radius=4,
                 denoise_footprints=8.0, edge_side_radius=1, hole_fill=7, edge_readmit=True, edge_band_radius=3,
                 step_split_radius=20, stages=STEP_SPLIT_STAGES, pattern_halo="auto",
                 refine_through_halo=False, lens_variance_lr_factor=16.0, lens_lambda_reg=0.5, **HASHGRID),
    "accurate": dict(matmul="tf32", compile=False, iters=2000, rays=1024, grid_levels=8, grid_gradient="finite_difference_4", grid_start_levels=2, grid_level_every=100, variance_lr_factor=4.0, refine_range=3.0,
                     refine_max_misfit=0.024, search_doubt=True, search_repair=True, repair_min_component=100, repair_grow=True,
                     surface_weight=1.0, surface_after=1.0, free_space=1.0, uniform_fill=True, edge_readmit=True,
                     denoise_radius=4,
                     denoise_footprints=8.0, edge_side_radius=1, hole_fill=7, edge_band_radius=3, step_split_radius=20,
                     stages=STEP_SPLIT_STAGES, pattern_halo="auto", refine_through_halo=False,
                     lens_variance_lr_factor=16.0, lens_lambda_reg=0.5,
                     **HASHGRID),
    "cpu-hashgrid": dict(refine_range=3.0, refine_max_misfit=0.024, search_doubt=True, search_repair=True, repair_min_component=100, repair_grow=True, uniform_fill=True,
                         denoise_radius=2, denoise_footprints=4.0, doubt_confidence=0.9, min_confidence=0.65, edge_side_radius=1,
                         hole_fill=7, edge_band_radius=2, stages=EDGE_BAND_STAGES,
                         grid_gradient="finite_difference_4", iters=1500, rays=384, n_samples=24, n_importance=16, up_sample_steps=2, search_step_mm=2.0,
                         mc_resolution=192, checkpoint_every=250, log_every=25, grid_levels=8, grid_log2_table=15,
                         pattern_halo="auto", refine_through_halo=False, lens_variance_lr_factor=16.0,
                         lens_lambda_reg=0.5, **HASHGRID),
}


@pytest.mark.parametrize("name", list(FLAT_PRESETS))
def test_presets_hold_the_flat_values(name):
    expect = {**FLAT_DEFAULTS, **FLAT_PRESETS[name]}
    cfg = PRESETS[name]
    assert set(OPTIONS) == set(expect)
    assert {k: cfg.get(k) for k in OPTIONS} == expect
    assert cfg.schedule.iters == expect["iters"] and cfg.init.iters == expect["init_iters"] and cfg.init.method == "search"
    assert set(PRESET_SUMMARIES) == set(PRESETS)


def test_preset_copies_and_flat_overrides():
    cfg = preset("tiny", iters=50, init_iters=20, init="sphere", device="cpu", skip=None)
    assert (cfg.schedule.iters, cfg.init.iters, cfg.init.method, cfg.runtime.device) == (50, 20, "sphere", "cpu")
    cfg.schedule.iters = 7
    assert PRESETS["tiny"].schedule.iters == 300  # presets are never changed through a copy
    with pytest.raises(ConfigError, match="unknown option 'iterations'"):
        preset("tiny", iterations=5)
    with pytest.raises(ConfigError, match="unknown preset 'quick'; presets: paper, tuned, cpu, tiny, fast, accurate"):
        preset("quick")


def test_parse_assignments_as_on_the_command_line():
    assert parse_assignments(["iters=300", "field=hashgrid", "surface_in_front=true", "lr=1e-3"]) == {
        "iters": 300, "field": "hashgrid", "surface_in_front": True, "lr": 1e-3}
    for bad, says in (["iters"], "expected KEY=VALUE"), (["no_such=1"], "'no_such=1'"), (["iters=-3"], "iters"):
        with pytest.raises(ConfigError, match=says):
            parse_assignments(bad)


@pytest.mark.parametrize("option,value,allowed", [
    ("lr_decay", "cos", "one of none, cosine"),  # used to mean cosine silently
    ("rays", 0, "an integer >= 1"),
    ("iters", 1.5, "an integer >= 1"),
    ("iters", 0, "an integer >= 1"),  # used to run only the warm-up and exit 0
    ("iters", -5, "an integer >= 1"),
    ("mc_resolution", 0, "an integer >= 16"),  # used to fail deep inside marching cubes
    ("min_confidence", -0.1, "a number >= 0 and <= 1"),
    ("min_confidence", 1.5, "a number >= 0 and <= 1"),
    ("refine_range", -1.0, "a number >= 0"),
    ("lr", 0.0, "a number > 0"),
    ("lambda_sc", math.nan, "a number >= 0"),
    ("lr_final", 1.5, "a number >= 0 and <= 1"),
    ("pattern_blur", -1.0, "a number >= 0 or auto"),
    ("pattern_blur", "sharp", "a number >= 0 or auto"),
    ("incremental", "yes", "true or false"),
    ("init", "zero", "one of search, sphere, camera"),
    ("device", "gpu", "auto, cpu, cuda or cuda:N"),
    ("skip", 0, "an integer >= 1 or none"),
    ("backend", None, "one of warp, torch"),
    ("field", "cnn", "one of mlp, hashgrid"),
    ("grid_finest", "fine", "an integer >= 1 and <= 65536 or auto"),
    ("grid_levels", 0, "an integer >= 1 and <= 64"),
    ("grid_gradient", "exact", "one of finite_difference, finite_difference_4, analytic"),
    ("grid_table_lr_factor", 0.0, "a number > 0"),
])
def test_validation_names_option_value_and_what_is_allowed(option, value, allowed):
    with pytest.raises(ConfigError) as e:
        preset("paper", **{option: value})
    msg = str(e.value)
    assert f"option {option} " in msg and repr(value) in msg and allowed in msg


def test_rules_between_options():
    with pytest.raises(ConfigError, match="n_importance: 30 is not a multiple of up_sample_steps \\(4\\)"):
        preset("paper", n_importance=30)
    with pytest.raises(ConfigError, match="skip: 8 must be below layers \\(8\\)"):
        preset("paper", skip=8)
    with pytest.raises(ConfigError, match="grid_start_levels: 9 must not exceed grid_levels \\(8\\)"):
        preset("cpu-hashgrid", grid_start_levels=9)
    with pytest.raises(ConfigError, match="grid_finest: 8 must not be below grid_base \\(16\\), or auto"):
        preset("accurate", grid_finest=8)
    with pytest.raises(ConfigError, match="repair_grow: true needs search_repair: true"):
        preset("paper", repair_grow=True)
    cfg = preset("paper")
    cfg.schedule.lr_decay = "exp"  # set by hand: validate() (which Trainer calls) still catches it
    with pytest.raises(ConfigError, match="lr_decay"):
        cfg.validate()


def test_option_names_are_unique_and_documented():
    assert len(OPTIONS) == sum(len(dataclasses.fields(cls)) for cls in SECTIONS.values())
    for opt in OPTIONS.values():
        assert opt.help and opt.section in SECTIONS
    assert OPTIONS["init_iters"].section == "init" and OPTIONS["init_iters"].key == "iters"


def test_yaml_round_trip_partial_files_and_errors(tmp_path):
    cfg = preset("cpu", iters=10, skip=None, pattern_blur=0.75, device="cpu")
    save_config(tmp_path / "config.yaml", cfg, fitted={"pattern_blur_px": 0.9, "fit_mse": {0.25: 1e-3}})
    assert load_config(tmp_path / "config.yaml") == cfg  # the fitted section is read past
    (tmp_path / "part.yaml").write_text("schedule:\n  lr: 1e-3\ninit: {method: sphere}\n")
    part = load_config(tmp_path / "part.yaml", base=PRESETS["tiny"])
    assert part.schedule.lr == 1e-3 and part.init.method == "sphere" and part.field.hidden == 48  # YAML's "1e-3" string
    cases = {"sched:\n  iters: 3\n": "unknown section 'sched'; sections: field, sampling, schedule",
             "schedule:\n  iter: 3\n": "unknown option schedule.iter; schedule has iters, lr",
             "schedule:\n  lr_decay: cos\n": "option lr_decay (schedule.lr_decay): 'cos' is not allowed",
             "schedule: 3\n": "section schedule must be a mapping",
             "- 1\n- 2\n": "expected a mapping of sections"}
    for text, msg in cases.items():
        (tmp_path / "bad.yaml").write_text(text)
        with pytest.raises(ConfigError, match="bad.yaml") as e:
            load_config(tmp_path / "bad.yaml")
        assert msg in str(e.value)
    with pytest.raises(ConfigError, match="config file not found"):
        load_config(tmp_path / "missing.yaml")


def test_a_removed_option_in_an_old_config_is_read_past(tmp_path):
    """A config.yaml written before search_confirm was removed still loads: off silently, on with a warning that
    names the file and the option. Only in its own section, and no longer as an option to set."""
    (tmp_path / "old.yaml").write_text("extraction:\n  search_confirm: false\n  min_confidence: 0.5\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert load_config(tmp_path / "old.yaml").extraction.min_confidence == 0.5
    (tmp_path / "on.yaml").write_text("extraction:\n  search_confirm: true\n")
    with pytest.warns(UserWarning, match="on.yaml: option extraction.search_confirm was removed .*ignored"):
        assert load_config(tmp_path / "on.yaml") == TrainConfig()
    (tmp_path / "wrong.yaml").write_text("schedule:\n  search_confirm: true\n")
    with pytest.raises(ConfigError, match="unknown option schedule.search_confirm"):
        load_config(tmp_path / "wrong.yaml")
    with pytest.raises(ConfigError, match="unknown option 'search_confirm'"):
        preset("tuned", search_confirm=True)


def parse(argv):
    args = cli.build_parser(argv).parse_args(argv)
    return cli._config_from_args(args)


def test_cli_flags_are_generated_for_every_option():
    for name, opt in OPTIONS.items():
        flag = "--" + name.replace("_", "-")
        default = PRESETS["tiny"].get(name)
        if opt.is_bool:
            argv, expect = ["--no-" + flag[2:] if default else flag], not default
        elif opt.choices and opt._numeric() is None:
            expect = next(c for c in opt.choices if c != default)
            argv = [flag, expect]
        elif name == "device":
            argv, expect = [flag, "cpu"], "cpu"
        elif opt.is_list:  # the extraction's stages, comma-separated
            expect = ("marching_cubes", "depth", "confidence")
            argv = [flag, ",".join(expect)]
        else:  # a value that differs from tiny's and satisfies the rules between options
            expect = {"grid_start_levels": 3, "grid_finest": 64, "grid_log2_table": 12,
                      "surface_band_mm": 1.0, "edge_side_margin": 0.6, "hole_fill_footprints": 1.0}.get(name, {int: 2, float: 0.5}[opt._numeric()])
            if opt.min is not None and expect < opt.min:  # e.g. mc_resolution >= 16
                expect = {int: int, float: float}[opt._numeric()](opt.min) + 1
            assert expect != default
            argv = [flag, str(expect)]
        needs = ["--search-repair"] if name == "repair_grow" else []  # a rule between options
        _, cfg, _ = parse(["reconstruct", "scan", "--out", "o", "--preset", "tiny", *argv, *needs])
        assert cfg.get(name) == expect, name


def test_cli_help_shows_presets_and_the_chosen_presets_defaults(capsys):
    for argv, shown in ((["reconstruct", "--preset", "tiny", "--help-all"], "(preset tiny: 48)"),
                        (["demo", "--preset=paper", "--help-all"], "(preset paper: 256)")):
        with pytest.raises(SystemExit):
            cli.build_parser(argv).parse_args(argv)
        out = capsys.readouterr().out
        assert shown in " ".join(out.split())  # argparse wraps the help
        for name in PRESETS:  # every preset, one line each
            assert sum(line.strip().startswith(name + " ") for line in out.splitlines()) == 1, name


def test_cli_config_file_then_flags(tmp_path):
    (tmp_path / "c.yaml").write_text("schedule: {iters: 77, lr: 0.002}\nfield: {hidden: 32}\n")
    name, cfg, dev = parse(["reconstruct", "scan", "--out", "o", "--preset", "tiny", "--device", "cpu", "--config",
                            str(tmp_path / "c.yaml"), "--iters", "5"])
    assert name == "tiny" and str(dev) == "cpu"
    assert (cfg.schedule.iters, cfg.schedule.lr, cfg.field.hidden, cfg.field.layers) == (5, 0.002, 32, 3)
    assert cfg.runtime.device == "cpu"


def test_cli_bad_options_and_internal_errors(tmp_path, capsys, monkeypatch):
    with pytest.raises(SystemExit):  # argparse rejects a bad value with the option's message
        cli.main(["reconstruct", "scan", "--out", "o", "--lr-decay", "cos"])
    assert "'cos' is not allowed; it takes one of none, cosine" in capsys.readouterr().err
    (tmp_path / "bad.yaml").write_text("schedule: {iterz: 3}\n")
    assert cli.main(["reconstruct", "scan", "--out", "o", "--device", "cpu", "--config", str(tmp_path / "bad.yaml")]) == 2
    err = capsys.readouterr().err
    assert "unknown option schedule.iterz" in err and len(err.strip().splitlines()) == 1

    def broken(args):
        raise ValueError("an internal bug")

    monkeypatch.setattr(cli.decode, "cmd_evaluate", broken)
    with pytest.raises(ValueError, match="an internal bug"):  # a bug keeps its traceback
        cli.main(["evaluate", "pred.npy", "scan"])


def test_train_config_is_importable_from_slwarp():
    import slwarp

    assert slwarp.TrainConfig is TrainConfig and slwarp.preset is preset and slwarp.load_config is load_config


def test_resumable_options_are_marked_once():
    from slwarp.neural.config import OPTIONS, RESUMABLE

    # more iterations, logging and where the run executes may change on resume; what it computes may not
    assert {"iters", "log_every", "checkpoint_every", "device", "mc_resolution"} <= set(RESUMABLE)
    assert not {"lr", "seed", "rays", "hidden", "pattern_blur", "matmul"} & set(RESUMABLE)
    fixed = preset("tiny").fixed_options()
    assert set(fixed) == set(OPTIONS) - set(RESUMABLE) and fixed["seed"] == 0


def test_field_kind_network_and_default_presets():
    from slwarp.neural.config import DEFAULT_PRESET, default_preset_name

    mlp, grid = PRESETS["cpu"].field, PRESETS["cpu-hashgrid"].field
    assert mlp.network() == dict(kind="mlp", hidden=64, layers=4, skip=2, n_freqs=6)  # grid options do not count
    assert grid.network() == dict(kind="hashgrid", grid_levels=8, grid_log2_table=15, grid_base=16, grid_finest="auto",
                                  grid_hidden=64, grid_layers=1, grid_activation="softplus",
                                  grid_gradient="finite_difference_4", grid_table_lr_factor=10.0, grid_start_levels=2,
                                  grid_level_every=150)
    assert default_preset_name("cuda") == DEFAULT_PRESET["cuda"] and default_preset_name("cpu") == DEFAULT_PRESET["cpu"]
    assert default_preset_name("mps") == DEFAULT_PRESET["cpu"]
    assert set(DEFAULT_PRESET.values()) <= set(PRESETS)
    assert "paper's recipe" in PRESET_SUMMARIES["paper"]
    # the CLI flag of the field kind
    _, cfg, _ = parse(["reconstruct", "scan", "--out", "o", "--preset", "tiny", "--field", "hashgrid", "--grid-finest",
                       "256"])
    assert (cfg.field.kind, cfg.field.grid_finest, cfg.field.hidden) == ("hashgrid", 256, 48)


def test_make_field_builds_each_kind():
    import torch

    from slwarp.neural.fields import HashGridSDF, NeuSField, Volume, auto_finest_resolution, make_field

    volume = Volume((-395.0, -300.0, 440.0), (395.0, 300.0, 1110.0))  # 790 mm along x, as the built-in rigs' bunny
    # the pixel footprint at 775 mm (the middle of 450..1100): 775 / 450 = 1.72 mm on the small rig -> 459 cells
    # -> 512; 775 / 1800 = 0.43 mm on the default rig -> 1835 cells -> 2048
    assert auto_finest_resolution(volume, 775 / 450) == 512
    assert auto_finest_resolution(volume, 775 / 1800) == 2048
    assert auto_finest_resolution(volume, 1e4) == 1
    with pytest.raises(ValueError, match="must be > 0 mm"):
        auto_finest_resolution(volume, 0.0)
    assert isinstance(make_field(PRESETS["cpu"].field, volume), NeuSField)
    cfg = preset("cpu-hashgrid", grid_hidden=32, grid_layers=2, grid_gradient="analytic", grid_activation="relu").field
    f = make_field(cfg, volume, pixel_mm=775 / 450)
    assert isinstance(f, HashGridSDF)
    assert (f.layout.levels, f.layout.log2_table_size, f.layout.base_resolution, f.layout.finest_resolution) == (8, 15, 16, 512)
    assert (f.gradient, f.activation, f.n_active, int(f.active)) == ("analytic", "relu", 2, 2)
    assert [lin.weight.shape[0] for lin in f.linears] == [32, 32, 1]
    assert make_field(preset("accurate", grid_finest=1024).field, volume).layout.finest_resolution == 1024
    # the starting surface: NeuS's sphere of radius 0.5 (normalised) at the volume's centre
    centre = torch.tensor(volume.center, dtype=torch.float32)
    assert float(f(centre[None]).detach()) == pytest.approx(-0.5 * volume.scale, abs=1.0)
    far = make_field(cfg, volume, pixel_mm=1.7, init="camera", far=1100.0)
    assert float(far(torch.tensor([[0.0, 0.0, 600.0]])).detach()) == pytest.approx(500.0, abs=1.0)
    with pytest.raises(ValueError, match="needs the pixel footprint"):
        make_field(cfg, volume)


def test_the_config_imports_no_implementation_module_nor_torch():
    # the config holds the defaults (CONTRAST_THRESHOLD, REFINE_MAX_MISFIT, DEVICE_PATTERN) that the implementation
    # imports from it; the other way round would be an import cycle and would load torch for `--help`
    code = ("import sys, slwarp.neural.config\n"
            "print(' '.join(sorted(m for m in sys.modules if m.split('.')[0] in ('slwarp', 'torch', 'warp', 'numpy'))))")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    loaded = set(run.stdout.split())
    assert {"slwarp.neural.config", "slwarp.neural.config.presets"} <= loaded
    assert loaded <= {"slwarp", "slwarp.neural"} | {m for m in loaded if m.startswith("slwarp.neural.config")}, loaded
    from slwarp.neural import pattern_model
    from slwarp.neural.config import CONTRAST_THRESHOLD, REFINE_MAX_MISFIT

    assert pattern_model.CONTRAST_THRESHOLD is CONTRAST_THRESHOLD == TrainConfig().sampling.contrast_threshold
    assert {preset(name).extraction.refine_max_misfit for name in ("tuned", "fast", "accurate", "cpu-hashgrid")} == {
        REFINE_MAX_MISFIT}
