"""What a user waits for: `slwarp reconstruct SCAN --out DIR` as a fresh process, from a scan on disk to its outputs
on disk, with caches empty (a new machine) and filled (the run before filled them), and where the time goes.

    python -m bench.command_wall --preset fast --runs 3 --cold          # CUDA: bunny, default rig; run 1 on empty caches
    python -m bench.command_wall --preset fast --bytecode warm          # Python's bytecode compiled first, as a user's
    python -m bench.command_wall --smoke                                # CPU: small rig, tiny settings (a smoke test)
    python -m bench.command_wall --preset fast --bytecode warm --sample # each run under bench.stack_sampler
    python -m bench.command_wall --scan data/real/capture_0/scan --preset accurate   # a scan on disk (a real capture)

One simulated scan (made once into the work folder), or the scan --scan names. Then --runs fresh processes, one
after another, each the command a user types (`python -m slwarp reconstruct SCAN --preset P --out DIR --quiet`), timed from spawn to exit.
The caches a machine keeps between commands (Warp's kernels, Inductor's and Triton's compiled graphs) live in
<work>/caches: with --cold the first run finds them empty. Python's own bytecode cache: `--bytecode as-is` leaves it
as the machine has it (some hosts run with PYTHONDONTWRITEBYTECODE and compile every module from source in every
process); `--bytecode warm` compiles the installed packages into <work>/pycache first (PYTHONPYCACHEPREFIX), as a
user's machine, which keeps its bytecode caches, has them.

A single scan's command forks (slwarp.cli.loader): the scan is loaded by the parent beside the child's imports, so
"scan load" is the child's wait for it (and for the runtimes' start), and "exit" ends when the parent returns, before
the child's CUDA teardown. The breakdown comes from the command's own marks ($SLWARP_TIMELINE, slwarp.timeline) and
its timings.json: the interpreter's start, imports, scan load, until the reconstruction starts (device start, config),
setup (depth search, blur fit), training, extraction, outputs, the report, and the interpreter's exit. Writes
<out>/<stem>.json and .md.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

from bench import scan_on_disk, write_study
from bench.batch_throughput import compile_cache_env

REPO = Path(__file__).resolve().parents[1]
SMOKE_SET = ["iters=3", "init_iters=2", "mc_resolution=32", "rays=64"]
PHASES = (("interpreter", "interpreter"), ("imports", "imports"), ("scan", "scan load"), ("before", "to reconstruct()"),
          ("setup", "setup"), ("train", "training"), ("extract", "extraction"), ("outputs", "metrics, outputs"),
          ("report", "report"), ("teardown", "exit"))


def option_flags(items: list[str]) -> list[str]:
    """KEY=VALUE options -> the reconstruct command's flags (`--key value`, `--key` / `--no-key` for booleans)."""
    from slwarp.neural.config import OPTIONS, ConfigError, parse_assignments

    try:
        values = parse_assignments(items)
    except ConfigError as e:
        raise SystemExit(f"--set {e}") from None
    flags = []
    for key, value in values.items():
        flag = "--" + key.replace("_", "-")
        if OPTIONS[key].is_bool:
            flags.append(flag if value else "--no-" + flag[2:])
        else:
            flags += [flag, str(value)]
    return flags


def breakdown(spawn: float, end: float, marks: dict, timings: dict) -> dict:
    """Seconds per phase (PHASES) of one command from its marks (wall clock) and timings.json."""
    start = marks["reconstruct"]  # timings.json counts from here; its total_s ends before the files are written
    return {"interpreter": marks["started"] - spawn, "imports": marks["imports"] - marks["started"],
            "scan": marks["scan loaded"] - marks["imports"],
            "before": start - marks["scan loaded"], "setup": timings["setup_s"], "train": timings["train_s"],
            "extract": timings["depth_map_s"] - timings["setup_s"] - timings["train_s"],
            "outputs": marks["reconstructed"] - start - timings["depth_map_s"],
            "report": marks["exit"] - marks["reconstructed"], "teardown": end - marks["exit"],
            "to_depth_map": start + timings["depth_map_s"] - spawn}


def process_env(work: Path, empty: bool, smoke: bool) -> tuple[Path, dict]:
    """(the caches folder <work>/caches, emptied first when `empty`; the environment of a fresh process that keeps
    its caches there: Warp's kernels but with `smoke`, Inductor's and Triton's)."""
    caches = work / "caches"
    if empty:
        shutil.rmtree(caches, ignore_errors=True)
    caches.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "PYTHONUNBUFFERED": "1", **compile_cache_env(caches)}
    if not smoke:  # the CPU's Warp kernels compile for minutes: the smoke test keeps the user's kernel cache
        env["SLWARP_KERNEL_CACHE"] = str(caches / "warp")
    return caches, env


def run_command(cmd: list[str], env: dict, out: Path, samples: Path | None = None) -> dict:
    """One fresh process of `cmd` (`python -m MODULE ...`): its wall time from spawn to exit and, when it succeeded,
    its breakdown; with `samples` (a folder) run under bench.stack_sampler, and the report of the process that
    reconstructed (row["sampled"])."""
    tl = out.parent / f"{out.name}.timeline.jsonl"
    tl.unlink(missing_ok=True)
    if samples is not None:
        shutil.rmtree(samples, ignore_errors=True)
        cmd = [cmd[0], "-m", "bench.stack_sampler", str(samples), *cmd[1:]]
    spawn = time.time()
    p = subprocess.run(cmd, cwd=REPO, env={**env, "SLWARP_TIMELINE": str(tl)}, capture_output=True, text=True)
    end = time.time()
    row = {"wall_s": end - spawn, "rc": p.returncode}
    if p.returncode:
        row["error"] = (p.stdout + p.stderr).strip()[-1500:]
        return row
    marks, pid = {}, None
    for line in tl.read_text().splitlines():
        doc = json.loads(line)
        marks.update({k: v for k, v in doc["marks"]})
        pid = doc["pid"]
    timings = json.loads((out / "timings.json").read_text())
    row.update(breakdown(spawn, end, marks, timings))
    row["setup_phases"] = timings.get("setup_phases_s", {})
    row["first_steps"] = timings.get("first_steps_s", [])
    if samples is not None:
        from bench import stack_sampler

        row["sampled"] = stack_sampler.report(stack_sampler.load(samples, pid), marks, timings)
    return row


def compile_bytecode(prefix: Path) -> float:
    """Compile the interpreter's standard library, its installed packages and the project into `prefix`
    (PYTHONPYCACHEPREFIX); seconds."""
    import site
    import sysconfig

    # the standard library too: with PYTHONPYCACHEPREFIX set, Python looks for every module's bytecode under the
    # prefix only, so a standard library left out compiles from source in every run (about 120 modules, 0.55 s of a
    # fresh `fast` command on an H100 host), which a user's machine, whose caches sit beside the sources, never does
    paths = sysconfig.get_paths()
    roots = {paths["stdlib"], paths["platstdlib"], paths["purelib"], paths["platlib"], *site.getsitepackages(),
             *(p for p in sys.path if p.endswith(("site-packages", "dist-packages")) or "/tmp/site" in p),
             str(REPO / "slwarp"), str(REPO / "kernels")}
    t = time.perf_counter()
    subprocess.run([sys.executable, "-m", "compileall", "-q", "-j", "0", *sorted(r for r in roots if Path(r).is_dir())],
                   env={**os.environ, "PYTHONPYCACHEPREFIX": str(prefix)}, capture_output=True)
    return time.perf_counter() - t


def host_baseline(env: dict, count: int = 3) -> dict:
    """The host the runs ran on: its CPU model and cores, and `python -c "import torch"` timed `count` times as fresh
    processes in the runs' environment (s): the part of every command's imports that no change of slwarp's moves,
    which differs between hosts by a second (bench/results: 1.5-2.6 s of imports for the same code)."""
    model = platform.processor() or platform.machine()
    try:
        model = next(line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                     if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    times = []
    for _ in range(count):  # after the runs: their caches and bytecode are the import's too
        t = time.perf_counter()
        subprocess.run([sys.executable, "-c", "import torch"], env=env, capture_output=True)
        times.append(time.perf_counter() - t)
    return {"cpu": model, "cores": os.cpu_count(), "torch_import_s": times}


def markdown(doc: dict) -> str:
    s = doc["setup"]
    lines = [f"# The command's wall time, preset `{s['preset']}`, {s['scene']} ({s['rig']} rig), {doc['device']}, "
             f"{doc['date']}", "", f"`{doc['bench_command']}`", "",
             f"Each run: `{' '.join(doc['command'])}` as a fresh process, timed from spawn to exit. Caches (Warp "
             "kernels, Inductor, Triton) in the work folder" + (", emptied before run 1" if s["cold"] else "")
             + f"; Python bytecode {s['bytecode']}"
             + (f" (compiled into a cache prefix first, {doc['bytecode_s']:.0f} s)" if s["bytecode"] == "warm" else "")
             + ". Phases in seconds (marks of the command and its timings.json)."
             + (f" Host: {doc['host']['cpu']}, {doc['host']['cores']} cores; `python -c \"import torch\"` took "
                + " / ".join(f"{t:.2f}" for t in doc["host"]["torch_import_s"]) + " s in the runs' environment "
                "(hosts differ by about a second there)." if doc.get("host") else ""), "",
             "| run | caches | wall s | to depth map s | " + " | ".join(t for _, t in PHASES) + " |",
             "|---|---|---:|---:|" + "---:|" * len(PHASES)]
    for i, r in enumerate(doc["runs"], 1):
        if r.get("error"):
            why = r["error"][-200:].replace("\n", " / ").replace("|", "\\|")
            lines.append(f"| {i} | {r['caches']} | {r['wall_s']:.1f} | failed: {why} |" + "|" * len(PHASES))
            continue
        lines.append(f"| {i} | {r['caches']} | {r['wall_s']:.2f} | {r['to_depth_map']:.2f} | "
                     + " | ".join(f"{r[k]:.2f}" for k, _ in PHASES) + " |")
    return "\n".join(lines + setup_table(doc["runs"]) + sampled_sections(doc["runs"]))


def sampled_sections(runs: list[dict]) -> list[str]:
    """With --sample: each run's report of bench.stack_sampler."""
    from bench import stack_sampler

    lines = []
    for i, r in enumerate(runs, 1):
        if r.get("sampled"):
            lines += [""] + stack_sampler.markdown(r["sampled"], f"Run {i} ({r['caches']} caches), sampled every "
                                                   f"{os.environ.get('SLWARP_SAMPLE_MS', '2')} ms")
    if lines:
        lines = ["", "## Where the main thread was (bench.stack_sampler; it slows a run by a few per cent)", *lines]
    return lines


def setup_table(runs: list[dict]) -> list[str]:
    """The setup phase split by the trainer's own marks (host seconds) and the host time of the first steps."""
    names = list(dict.fromkeys(k for r in runs for k in r.get("setup_phases", {})))
    if not names:
        return []
    steps = max(len(r.get("first_steps", [])) for r in runs)
    lines = ["", "Setup by the trainer's marks and the first training steps (host seconds; a fresh process pays its "
             "first calls here: CUDA and Warp start, module loads, lazy imports, graph capture).", "",
             "| run | " + " | ".join(names) + " | " + " | ".join(f"step {i + 1}" for i in range(steps)) + " |",
             "|---|" + "---:|" * (len(names) + steps)]
    for i, r in enumerate(runs, 1):
        if r.get("error"):
            continue
        ph, st = r.get("setup_phases", {}), r.get("first_steps", [])
        lines.append(f"| {i} | " + " | ".join(f"{ph[n]:.2f}" if n in ph else "" for n in names) + " | "
                     + " | ".join(f"{st[j]:.3f}" if j < len(st) else "" for j in range(steps)) + " |")
    return lines


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default=None, help="default: the device's default preset (tiny with --smoke)")
    p.add_argument("--scene", default="bunny")
    p.add_argument("--rig", default=None, help="default: default on CUDA, small on the CPU")
    p.add_argument("--scan", default=None, help="a scan folder to reconstruct instead of the simulated scene")
    p.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="options given to the command as flags")
    p.add_argument("--runs", type=int, default=3, help="fresh processes, one after another")
    p.add_argument("--cold", action="store_true", help="empty the caches before the first run")
    p.add_argument("--bytecode", choices=["as-is", "warm"], default="as-is")
    p.add_argument("--work", default="/tmp/slwarp-command-wall", help="the scan, the caches and the outputs")
    p.add_argument("--smoke", action="store_true", help="CPU, small rig, tiny preset and a few iterations")
    p.add_argument("--host-imports", type=int, default=3, help="time `python -c 'import torch'` this many times "
                   "after the runs, the host's share of the imports (0: not)")
    p.add_argument("--sample", action="store_true", help="run each command under bench.stack_sampler and report where "
                   "its main thread was, per phase")
    p.add_argument("--stem", default=None)
    p.add_argument("--out", default=str(REPO / "bench" / "results"))
    args = p.parse_args(argv)
    if args.runs < 1:
        raise SystemExit("--runs must be >= 1")
    cuda = not args.smoke and bool(shutil.which("nvidia-smi")) and subprocess.run(
        ["nvidia-smi", "-L"], capture_output=True).returncode == 0
    if args.smoke:
        args.preset, args.rig, args.scene = args.preset or "tiny", args.rig or "small", "spheres"
        args.set = SMOKE_SET + args.set
    from slwarp.neural.config import default_preset_name

    args.preset = args.preset or default_preset_name("cuda" if cuda else "cpu")
    args.rig = args.rig or ("default" if cuda else "small")
    flags = option_flags(args.set)
    work = Path(args.work)
    caches, env = process_env(work, args.cold, args.smoke)
    bytecode_s = None
    if args.bytecode == "warm":
        env["PYTHONPYCACHEPREFIX"] = str(work / "pycache")
        bytecode_s = compile_bytecode(work / "pycache")
    if args.scan:
        scan, args.scene = scan_on_disk(args.scan)
        args.rig = "its own"
    else:
        scan = work / f"scan-{args.scene}-{args.rig}"
    if not args.scan and not (scan / "scan.yaml").is_file():
        # the simulator's kernels in a cache of their own: the command's caches stay as --cold left them (the smoke
        # test keeps the user's kernel cache for both)
        sim_env = {**env, "SLWARP_KERNEL_CACHE": str(work / "simulator-kernels")} if not args.smoke else env
        made = subprocess.run([sys.executable, "-m", "slwarp", "simulate", "--scene", args.scene, "--rig", args.rig,
                               "--patterns", "random6", "--out", str(scan)], cwd=REPO, env=sim_env, capture_output=True,
                              text=True)
        if made.returncode:
            raise SystemExit(f"could not simulate the scan into {scan}:\n{made.stdout[-800:]}{made.stderr[-800:]}")
    command = ["python", "-m", "slwarp", "reconstruct", str(scan), "--preset", args.preset, "--out", "OUT", "--quiet",
               "--overwrite", *flags]
    runs = []
    for i in range(args.runs):
        warm = any(f.is_file() for f in caches.rglob("*"))  # files: the cache folders exist before anything is in them
        out = work / f"out-{i + 1}"
        row = {"caches": "filled" if warm else "empty",
               **run_command([sys.executable, *[str(out) if c == "OUT" else c for c in command[1:]]], env, out,
                             samples=work / f"samples-{i + 1}" if args.sample else None)}
        runs.append(row)
        print(f"run {i + 1} ({row['caches']} caches): " + (f"{row['wall_s']:.2f} s, depth map at {row['to_depth_map']:.2f} s"
                                                            if "error" not in row else f"failed:\n{row['error']}"), flush=True)
    device = "CPU"
    if cuda:
        device = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"], capture_output=True,
                                text=True).stdout.strip().splitlines()[0]
    doc = {"device": device, "date": str(datetime.date.today()), "command": command, "bytecode_s": bytecode_s,
           "host": host_baseline(env, args.host_imports) if args.host_imports > 0 else None,
           "bench_command": "python -m bench.command_wall " + " ".join(argv if argv is not None else sys.argv[1:]),
           "setup": {"preset": args.preset, "scene": args.scene, "rig": args.rig, "scan": args.scan, "set": args.set,
                     "cold": args.cold, "bytecode": args.bytecode, "smoke": args.smoke, "sample": args.sample},
           "runs": runs}
    stem = args.stem or f"command-wall-{'cuda' if cuda else 'cpu'}-{args.preset}"
    write_study(Path(args.out) / stem, doc, lambda d: markdown(d) + "\n")


if __name__ == "__main__":
    main()
