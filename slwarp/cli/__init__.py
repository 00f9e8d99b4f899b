"""The `slwarp` command: one subcommand per pipeline stage.

    slwarp info SCAN                      validate a scan and print its summary
    slwarp simulate --scene NAME ...      render a scan with exact ground truth (virtual scanner)
    slwarp decode SCAN --method M --out D classical decoding (Gray code, CGC, PMP, ...) + triangulation
    slwarp evaluate PRED SCAN             depth metrics of a depth map against the scan's ground truth
    slwarp reconstruct SCAN... --out D    the neural SDF method: train, then depth, mesh, point cloud (several
                                          scans: a batch, sharded over torchrun's processes; see slwarp.batch)
    slwarp design-patterns --rig R --out D   projector patterns optimised for a rig (slwarp.design)
    slwarp demo                           the paper's comparison on an embedded default scene

    slwarp --version                      slwarp's version, with torch's and Warp's

The training options of `reconstruct` and `demo` are generated from slwarp.neural.config.TrainConfig (flag,
type, choices, help and the chosen preset's default); `--config FILE.yaml` reads a config, and flags override it.
Their --help shows the common options (COMMON_OPTIONS), --help-all every one, --help-all SECTION one section's.

Bad input (a user error: a missing or malformed file, an option out of range) exits with status 2 and a
one-line message naming the file or option and the problem (SLWARP_DEBUG=1 shows the traceback instead); a
command line argparse rejects adds one line pointing to the command's --help, never the usage. Anything else is
a bug and keeps its traceback.

Modules: `scans` (info, simulate), `decode` (decode, evaluate), `neural` (reconstruct, watch, demo), `design`
(design-patterns), `options` (the options and help the commands share), `errors` (what is reported as bad input);
here the parser and `main`.
"""
from __future__ import annotations

import argparse
import os
import sys

from .. import timeline

timeline.mark("started")  # the interpreter has started and imported the command's module

# the commands, imported after the mark, which times the interpreter's start (they import nothing heavy at the top)
from .design import _add_design, cmd_design  # noqa: E402
from .decode import _add_decode, _add_evaluate, cmd_decode, cmd_evaluate  # noqa: E402
from . import loader  # noqa: E402
from .errors import _VALUE_ERRORS_ARE_USER_ERRORS, UserError, _interrupted, _report, _user_errors  # noqa: E402
from .neural import _add_demo, _add_reconstruct, _add_watch, cmd_demo, cmd_reconstruct, cmd_watch  # noqa: E402
from .options import COMMON_OPTIONS, _Parser, _Version, version_text  # noqa: E402
from .options import _config_from_args  # noqa: E402, F401 - re-exported: tests build configs with it
from .scans import _add_info, _add_simulate, cmd_info, cmd_simulate  # noqa: E402

# what others import from here: main, entry, build_parser, and these
__all__ = ["main", "entry", "build_parser", "version_text", "UserError", "COMMON_OPTIONS", "cmd_info", "cmd_simulate",
           "cmd_decode", "cmd_evaluate", "cmd_reconstruct", "cmd_watch", "cmd_demo", "cmd_design"]


def build_parser(argv=None) -> argparse.ArgumentParser:
    """The `slwarp` parser. argv (the command line to parse) picks the preset whose defaults --help shows, and the
    command whose options are built: the others get their name and summary only, so that `slwarp --help`, `slwarp
    --version` and the light commands do not load the training configuration (and torch). argv None: every command
    in full."""
    parser = _Parser(prog="slwarp",
                     description="Depth reconstruction with neural SDFs in camera + projector structured-light systems.")
    parser.add_argument("--version", action=_Version)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True
    argv = None if argv is None else list(argv)
    named = argv[0] if argv and "--version" not in argv else None  # the top level has no option taking a value
    for name, (summary, add) in _COMMANDS.items():
        p = sub.add_parser(name, help=summary)
        p.add_argument("--version", action=_Version)
        if argv is None or name == named:
            add(p, argv) if name in _TRAINING_COMMANDS else add(p)
    parser.commands = sub.choices
    return parser


# name: (summary in the command list, the function that adds its options)
_COMMANDS = {
    "demo": ("simulate a scene, reconstruct it with the neural SDF and with Gray code, compare", _add_demo),
    "info": ("validate a scan and print its summary (rig, frames, ground truth)", _add_info),
    "simulate": ("render a scan with exact ground truth on the virtual scanner", _add_simulate),
    "decode": ("decode a scan with a classical method and triangulate (depth map, point cloud)", _add_decode),
    "evaluate": ("depth metrics (MAE, RMSE, >1/2/5 mm, completeness) against a scan's ground truth, and how well a "
                 "confidence map ranks the errors", _add_evaluate),
    "reconstruct": ("depth, mesh and point cloud from a scan with the neural SDF method", _add_reconstruct),
    "design-patterns": ("projector patterns optimised for a rig's geometry, blur and noise (PNGs + a pattern-set file)",
                        _add_design),
    "watch": ("a scanning station: reconstruct each scan folder that appears in a folder, in one warm process",
              _add_watch),
}
_TRAINING_COMMANDS = ("demo", "reconstruct", "watch")  # their options come from TrainConfig (and the chosen preset)


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(argv)
    args, unknown = parser.parse_known_args(argv)
    if unknown:  # reported by the command's parser: its name and its --help
        parser.commands[args.command].error(f"unrecognized arguments: {' '.join(unknown)}")
    try:
        return int(args.func(args) or 0)
    except BrokenPipeError:  # output piped into `head` and the like
        return 0
    except _interrupted() as e:
        print(f"slwarp {args.command}: {e}", file=sys.stderr)
        return e.exit_status
    except _user_errors() as e:
        return _report(args, e)
    except ValueError as e:
        if args.command not in _VALUE_ERRORS_ARE_USER_ERRORS:
            raise
        return _report(args, e)
    except KeyboardInterrupt:
        print(f"slwarp {args.command}: interrupted", file=sys.stderr)
        return 130


def entry() -> None:
    """The `slwarp` console command and `python -m slwarp`: `main`, then the process ends as soon as its output is
    flushed. Why not a plain return: the interpreter's teardown (torch's, Warp's and CUDA's exit handlers, every
    module's objects freed) ran for seconds after the last output file was closed, while the user waited on the
    prompt; every file a command writes is closed (or renamed into place) before `main` returns."""
    loader.allow_fork()  # a single scan's `reconstruct` loads it in a process of its own (cli.loader)
    code = main()
    if "slwarp.devices" in sys.modules:  # imported by the command: a line held back by a runtime's start written out
        sys.modules["slwarp.devices"].runtimes_started()
    timeline.mark("exit")
    timeline.write()
    sys.stdout.flush()
    sys.stderr.flush()
    loader.report_exit(code)  # a split command's parent exits now, with this status
    os._exit(code)
