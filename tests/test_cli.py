"""The `slwarp` command as users meet it: --version, one-line option errors with a hint, short --help and
--help-all, per-preset defaults in the help, the start line of a run."""
from __future__ import annotations

import subprocess
import sys
from importlib import metadata

import pytest

from slwarp import cli
from slwarp.neural.config import OPTIONS, PRESETS, SECTIONS, preset
from slwarp.neural.describe import describe, total_iterations


def _exit(argv, capsys) -> tuple[int, str, str]:
    """(exit status, stdout, stderr) of `slwarp argv` run in this process."""
    try:
        status = cli.main(argv)
    except SystemExit as e:
        status = e.code
    out = capsys.readouterr()
    return status, out.out, out.err


def _help(argv, capsys) -> str:
    status, out, err = _exit(argv, capsys)
    assert status == 0 and not err, err
    return out


def test_version_answers_without_loading_torch():
    code = ("import sys; from slwarp.cli import main\n"
            "try:\n    main(['--version'])\nexcept SystemExit as e:\n    assert e.code == 0, e.code\n"
            "print('torch loaded' if 'torch' in sys.modules else 'torch not loaded')")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    first, last = run.stdout.strip().splitlines()
    assert first.startswith(f"slwarp {metadata.version('slwarp')} (torch {metadata.version('torch')}, warp ")
    assert last == "torch not loaded"


@pytest.mark.parametrize("command", ["info", "reconstruct"])
def test_version_of_a_command(capsys, command):
    status, out, _ = _exit([command, "--version"], capsys)
    assert status == 0 and out.startswith("slwarp ")


# (command line, the one error line, the command whose --help the hint names)
BAD_VALUES = [
    (["reconstruct", "--iters", "-5"], "slwarp reconstruct: error: --iters: -5 is not allowed; it takes an integer >= 1",
     "slwarp reconstruct"),
    (["reconstruct", "scan", "--out", "o", "--lr-decay", "cos"],
     "slwarp reconstruct: error: --lr-decay: 'cos' is not allowed; it takes one of none, cosine", "slwarp reconstruct"),
    (["demo", "--field", "grid"], "slwarp demo: error: --field: 'grid' is not allowed; it takes one of mlp, hashgrid",
     "slwarp demo"),
    (["simulate", "--bits", "3"], "slwarp simulate: error: --bits: invalid choice: 3 (choose from 0, 8, 16)",
     "slwarp simulate"),
    (["decode", "scan", "--method", "gc", "--out", "o", "--min-amplitude", "x"],
     "slwarp decode: error: --min-amplitude: invalid float value: 'x'", "slwarp decode"),
    (["evaluate", "pred.npy", "scan", "--bogus"], "slwarp evaluate: error: unrecognized arguments: --bogus",
     "slwarp evaluate"),
    (["info"], "slwarp info: error: the following arguments are required: scan", "slwarp info"),
    (["reconstruct", "scan", "--out", "o", "--per-device", "-1"],
     "slwarp reconstruct: error: --per-device: '-1' is not allowed; it takes an integer >= 0", "slwarp reconstruct"),
    (["recontsruct"], "slwarp: error: COMMAND: invalid choice: 'recontsruct' (choose from 'demo', 'info', "
     "'simulate', 'decode', 'evaluate', 'reconstruct', 'design-patterns', 'watch')", "slwarp"),
]


@pytest.mark.parametrize("argv,line,prog", BAD_VALUES, ids=[" ".join(c[0][:2]) for c in BAD_VALUES])
def test_bad_values_are_one_line_and_a_hint(capsys, argv, line, prog):
    status, out, err = _exit(argv, capsys)
    assert status == 2 and not out
    assert err.splitlines() == [line, f"see '{prog} --help'"]  # no usage dump


def test_rules_between_options_are_one_line(capsys):
    status, _, err = _exit(["reconstruct", "scan", "--out", "o", "--device", "cpu", "--preset", "tiny", "--skip", "5"],
                           capsys)
    assert status == 2
    assert err.splitlines() == ["slwarp reconstruct: error: option skip: 5 must be below layers (3), or none"]


@pytest.mark.parametrize("command", ["reconstruct", "demo"])
def test_help_is_short_and_help_all_lists_every_option(capsys, command):
    short = _help([command, "--preset", "cpu-hashgrid", "--help"], capsys)
    full = _help([command, "--preset", "cpu-hashgrid", "--help-all"], capsys)
    flags = {"--" + name.replace("_", "-") for name in OPTIONS}
    common = {"--" + name.replace("_", "-") for name in cli.COMMON_OPTIONS}
    shown = {w.strip("[],") for w in short.split() if w.startswith(("--", "[--"))}
    assert common <= shown and not (flags - common) & shown
    assert len(short.splitlines()) < 100 and len(full.splitlines()) > 3 * len(short.splitlines())
    assert f"'slwarp {command} --help-all'" in " ".join(short.split())
    assert flags <= {w.strip("[],") for w in full.split() if w.startswith(("--", "[--"))}
    for name in PRESETS:  # one line per preset, generated from its config
        line = next(x for x in short.splitlines() if x.strip().startswith(name + " "))
        assert describe(PRESETS[name]) in line


def test_help_all_of_one_section(capsys):
    out = _help(["reconstruct", "--help-all", "extraction"], capsys)
    assert "--mc-resolution" in out and "--denoise-radius" in out and "--iters" in out  # the section + the common ones
    assert "--grid-levels" not in out and "--lr " not in out
    status, _, err = _exit(["reconstruct", "--help-all", "fields"], capsys)
    assert status == 2 and "invalid choice: 'fields'" in err


def _option_help(out: str, flag: str) -> str:
    """The help text of `flag` in a --help output, on one line."""
    words = " ".join(out.split())
    start = words.index(f" {flag} ") + len(flag) + 2
    nxt = words.find(" --", start)
    return words[start:nxt]


def test_help_shows_each_presets_own_defaults(capsys):
    grid = _help(["reconstruct", "--preset", "cpu-hashgrid", "--help-all"], capsys)
    assert "(preset cpu-hashgrid: not used by the hashgrid field)" in _option_help(grid, "--hidden")
    assert "(preset cpu-hashgrid: 15)" in _option_help(grid, "--grid-log2-table")
    mlp = _help(["reconstruct", "--preset", "tuned", "--help-all"], capsys)
    assert "(preset tuned: 256)" in _option_help(mlp, "--hidden")
    assert "(preset tuned: not used by the mlp field)" in _option_help(mlp, "--grid-levels")
    switched = _help(["reconstruct", "--preset", "tuned", "--field", "hashgrid", "--help-all"], capsys)
    assert "not used by the hashgrid field" in _option_help(switched, "--layers")
    assert "(preset tuned: 16)" in _option_help(switched, "--grid-levels")


def test_describe_names_the_real_field_and_iterations():
    assert describe(preset("cpu-hashgrid")) == ("hash grid 8 levels x 2^15 + MLP 1x64, 1800 iterations (300 warm-up), "
                                                "384 rays, 24+16 samples")
    assert describe(preset("paper")).startswith("MLP 8x256, 4300 iterations (300 warm-up), 2048 rays")
    assert describe(preset("paper", init="sphere")).startswith("MLP 8x256, 4000 iterations, ")
    assert "finest 512" in describe(preset("fast", grid_finest=512))
    assert total_iterations(preset("tiny", iters=30, init_iters=20)) == (50, 20)


def test_start_line_describes_the_run(tmp_path, capsys, monkeypatch):
    from slwarp.neural import reconstruct as reconstruct_module
    from slwarp.sim.simulate import SimOptions, simulate_scene

    simulate_scene("boxes", "random6", "small", SimOptions(seed=0), device="cpu").save(tmp_path / "scan")

    def stop(*args, **kwargs):  # the start line is all this test needs
        raise KeyboardInterrupt

    monkeypatch.setattr(reconstruct_module, "reconstruct", stop)
    status, out, err = _exit(["reconstruct", str(tmp_path / "scan"), "--out", str(tmp_path / "o"), "--device", "cpu",
                              "--preset", "cpu-hashgrid", "--iters", "40", "--init-iters", "10"], capsys)
    assert status == 130 and "interrupted" in err
    assert ("with preset 'cpu-hashgrid' (hash grid 8 levels x 2^15 + MLP 1x64, 50 iterations (10 warm-up), 384 rays, "
            "24+16 samples) on cpu") in out


def test_sections_have_help_groups(capsys):
    out = _help(["reconstruct", "--help-all"], capsys)
    for section in SECTIONS:
        assert f"\n{section}: " in out
