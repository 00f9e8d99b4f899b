"""Option helpers the commands share: the scan options (--frames, --allow-outside-paths), value parsers, the
training options generated from TrainConfig (--preset, --config, one flag per option) and the help they show
(short --help, --help-all), --version."""
from __future__ import annotations

import argparse
import math
import textwrap

from .errors import UserError

# ----------------------------------------------------------------------------------------------
# scan options and value parsers


OUTSIDE_PATHS_HELP = ("read the scan's files (frames, patterns, gt_depth, mask) that lie outside its folder, links "
                      "followed (default: only when its scan.yaml says allow_outside_paths: true; "
                      "--no-allow-outside-paths refuses them even then, for scans from others; see docs/inputs.md)")


def _add_outside_paths(p) -> None:
    p.add_argument("--allow-outside-paths", action=argparse.BooleanOptionalAction, default=None, help=OUTSIDE_PATHS_HELP)


FRAMES_HELP = ("frame selection, comma-separated tokens: frame names, indices, slices (0:7), role selectors "
               "(gray:col:bit=0-6:noinv, phase:row:period=40, white, random:size=20) or name globs (gc_col_b*)")


def _count_at_least(text: str, minimum: int) -> int:
    """`text` as an integer of at least `minimum`, else argparse's error saying so."""
    try:
        value = int(text)
    except ValueError:
        value = minimum - 1
    if value < minimum:
        raise argparse.ArgumentTypeError(f"{text!r} is not allowed; it takes an integer >= {minimum}")
    return value


def _non_negative_int(text: str) -> int:
    """argparse's `type` for a count of at least 0."""
    return _count_at_least(text, 0)


def _positive_int(text: str) -> int:
    """argparse's `type` for a count of at least 1."""
    return _count_at_least(text, 1)


def _parse_range(text: str | None):
    if text is None:
        return None
    try:
        near, far = (float(x) for x in text.replace(" ", "").split(","))
    except ValueError:
        raise UserError(f"--depth-range must be NEAR,FAR in mm, got {text!r}") from None
    if not (math.isfinite(near) and math.isfinite(far) and 0 < near < far):
        raise UserError(f"--depth-range needs 0 < NEAR < FAR, got {near}, {far}")
    return near, far


# ----------------------------------------------------------------------------------------------
# training options, generated from TrainConfig


# the TrainConfig options that `reconstruct --help` and `demo --help` show; --help-all shows every one
COMMON_OPTIONS = ("field", "iters", "rays", "device", "seed")


def _given(argv, flag: str) -> str | None:
    """The value of `flag` on a command line (--flag VALUE or --flag=VALUE; the last one wins), else None."""
    argv = list(argv or [])
    value = None
    for i, word in enumerate(argv):
        if word == flag and i + 1 < len(argv):
            value = argv[i + 1]
        elif word.startswith(flag + "="):
            value = word.split("=", 1)[1]
    return value


def _chosen_preset(argv) -> str:
    """The preset a reconstruct or demo command line runs with: --preset, else the device's default
    (slwarp.neural.config.DEFAULT_PRESET; the device from --device, default auto). Used for the defaults --help shows
    (and nothing else: the options' values come from `_config_from_args`), so a command line that asks for no help
    gets the CPU's default without importing torch to look for CUDA (about 1.5 s of a command's start, before
    `reconstruct --per-device` starts its workers)."""
    from ..neural.config import PRESETS, default_preset_name

    if _given(argv, "--preset") in PRESETS:
        return _given(argv, "--preset")
    if argv is not None and not any(a in ("-h", "--help") or a.startswith("--help-all") for a in argv):
        return default_preset_name("cpu")
    from ..devices import DeviceError, torch_device

    try:
        return default_preset_name(torch_device(_given(argv, "--device") or "auto"))
    except DeviceError:
        return default_preset_name("cpu")


def _add_config_options(p, preset_name: str, training: bool = True, argv=None) -> None:
    """--preset, --config, --help-all and one flag per TrainConfig option (grouped by section), with the help and
    the default the config declares (and, with `training`, which options may change on --resume); flags the user
    does not give stay out of the namespace. --help shows the COMMON_OPTIONS, --help-all every option."""
    import dataclasses

    from ..neural.config import DEFAULT_PRESET, OPTIONS, PRESET_SUMMARIES, PRESETS, SECTIONS
    from ..neural.describe import describe

    p.add_argument("--preset", choices=list(PRESETS), help="the starting configuration (see the list below); default: "
                   f"{DEFAULT_PRESET['cuda']} when the device is CUDA, else {DEFAULT_PRESET['cpu']}")
    p.add_argument("--config", metavar="FILE.yaml", help="a TrainConfig in YAML (sections field, sampling, schedule, "
                   "init, runtime, extraction; any option may be left out) applied over the preset; a run's "
                   "config.yaml reads back; flags override it")
    p.add_argument("--help-all", action=_HelpAll, choices=["all", *SECTIONS], help="show every option, grouped by "
                   f"section, and exit; with SECTION ({', '.join(SECTIONS)}) that section's")
    p.description = textwrap.fill(p.description, 100)
    width = max(map(len, PRESET_SUMMARIES))
    default_on = {v: k.replace("cuda", "CUDA").replace("cpu", "the CPU") for k, v in DEFAULT_PRESET.items()}
    # --help: one line per preset, generated from its config; --help-all: what each preset is for
    p.epilog = "presets (--help-all says what each is for):\n" + "\n".join(
        f"  {k:{width}s} {describe(cfg)}" + (f"; default on {default_on[k]}" if k in default_on else "")
        for k, cfg in PRESETS.items())
    p.epilog += (f"\n\n{len(OPTIONS) - len(COMMON_OPTIONS)} more options: '{p.prog} --help-all' lists every option "
                 f"by section, '{p.prog} --help-all SECTION' one section")
    p.epilog_all = "presets:\n" + "\n".join(
        textwrap.fill(v, 100, initial_indent=f"  {k:{width}s} ", subsequent_indent=" " * (width + 3))
        for k, v in PRESET_SUMMARIES.items())
    p.formatter_class = _Formatter
    defaults = PRESETS[preset_name]
    # the field that trains: the preset's, or --field's; the other kind's options do not apply to it
    kind = _given(argv, "--field") if _given(argv, "--field") in ("mlp", "hashgrid") else defaults.field.kind
    field_keys = dataclasses.replace(defaults.field, kind=kind).network()
    for section, cls in SECTIONS.items():
        title = cls.__doc__.splitlines()[0].rstrip(".")
        group = p.add_argument_group(f"{section}: {title[0].lower() + title[1:]}")
        for opt in (o for o in OPTIONS.values() if o.section == section):
            default = defaults.get(opt.name)
            shown = "none" if default is None else str(default).lower() if opt.is_bool else default
            if section == "field" and opt.key not in field_keys:
                shown = f"not used by the {kind} field"
            resumable = "; may change on resume" if opt.resumable and training else ""
            kw = dict(dest=opt.name, default=argparse.SUPPRESS,
                      help=f"{opt.help} (preset {preset_name}: {shown}{resumable})")
            if opt.is_bool:
                kw["action"] = argparse.BooleanOptionalAction
            else:
                kw["type"] = _option_parser(opt)
                kw["metavar"] = opt.metavar()
            action = group.add_argument("--" + opt.name.replace("_", "-"), **kw)
            if opt.name not in COMMON_OPTIONS:
                action.help_section = section


def _option_parser(opt):
    """argparse's `type` for an option: its parser, with errors as argparse reports them (naming the flag, so
    the config's 'option NAME (section.key): ' prefix is left out)."""

    def parse(text):
        from ..neural.config import ConfigError

        try:
            return opt.parse(text)
        except ConfigError as e:
            message, prefix = str(e), f"option {opt.name} ({opt.section}.{opt.key}): "
            raise argparse.ArgumentTypeError(message[len(prefix):] if message.startswith(prefix) else message) from None

    return parse


def _config_from_args(args):
    """(preset name, TrainConfig, torch device) of a reconstruct or demo command line: the preset, the --config
    file over it, the flags given over both; the device resolved."""
    from ..devices import torch_device
    from ..neural.config import OPTIONS, default_preset_name, load_config, preset

    given = {name: getattr(args, name) for name in OPTIONS if hasattr(args, name)}
    name = args.preset or default_preset_name(torch_device(given.get("device", "auto")))
    cfg = preset(name)
    if args.config:
        cfg = load_config(args.config, base=cfg)
    cfg = cfg.with_options(**given)
    dev = torch_device(cfg.runtime.device)
    return name, cfg.with_options(device=str(dev)), dev


# ----------------------------------------------------------------------------------------------
# help and version


class _Parser(argparse.ArgumentParser):
    """argparse as slwarp answers: a bad command line is one error line and a hint to --help (exit status 2, no
    usage dump); --help hides the options marked with a `help_section` (the rarely needed ones), which --help-all
    shows (every one, or one section's)."""

    help_shown: str | None = None  # set by --help-all: "all" or a section
    epilog_all: str | None = None  # the epilog of --help-all, when it differs from --help's

    def error(self, message):
        if message.startswith("argument "):  # argparse's "argument --iters: ...": the flag is enough
            message = message[len("argument "):]
        self.exit(2, f"{self.prog}: error: {message}\nsee '{self.prog} --help'\n")

    def format_help(self):
        hidden = [a for a in self._actions if getattr(a, "help_section", None)
                  and self.help_shown != "all" and a.help_section != self.help_shown]
        kept = [a.help for a in hidden], self.epilog
        for a in hidden:
            a.help = argparse.SUPPRESS
        if self.help_shown and self.epilog_all:
            self.epilog = self.epilog_all
        try:
            return super().format_help()
        finally:
            for a, h in zip(hidden, kept[0]):
                a.help = h
            self.epilog = kept[1]


class _Formatter(argparse.RawDescriptionHelpFormatter):
    """Option help wrapped at spaces only (a preset name such as cpu-hashgrid stays whole); the description and
    epilog as written."""

    def _split_lines(self, text, width):
        return textwrap.wrap(" ".join(text.split()), width, break_on_hyphens=False)


class _HelpAll(argparse.Action):
    """--help-all [SECTION]: the help with every option (or the common ones and SECTION's), then exit."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, choices=None, help=None):
        super().__init__(option_strings, dest, nargs="?", const="all", default=default, choices=choices,
                         metavar="SECTION", help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        parser.help_shown = values or "all"
        parser.print_help()
        parser.exit()


class _Version(argparse.Action):
    """--version: slwarp's version and those of torch and Warp, then exit."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS,
                 help="print the versions of slwarp, torch and Warp and exit"):
        super().__init__(option_strings, dest, nargs=0, default=default, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        print(version_text())
        parser.exit()


def version_text() -> str:
    """'slwarp X.Y.Z (torch A, warp B, Python C)' from the installed packages' metadata: nothing is imported, so it
    answers at once."""
    import platform
    from importlib import metadata

    def installed(dist):
        try:
            return metadata.version(dist)
        except metadata.PackageNotFoundError:
            return None

    own = installed("slwarp")
    if own is None:  # run from a source tree that is not installed
        from .. import __version__ as own
    others = [f"{name} {v}" for name, v in (("torch", installed("torch")), ("warp", installed("warp-lang"))) if v]
    return f"slwarp {own} ({', '.join([*others, f'Python {platform.python_version()}'])})"

