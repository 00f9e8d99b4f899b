"""A fresh process's first depth map: what `slwarp reconstruct SCAN` pays once per process on top of the
reconstruction itself (imports, the device's start-up, kernel loads, compiling or loading the training graphs,
CUDA-graph capture), against a second reconstruction of the same scan in the same process.

    python -m bench.first_scan --preset fast                     # CUDA: bunny, default rig, 3 fresh processes
    python -m bench.first_scan --preset fast --runs 2 --fresh    # the first process with empty caches
    python -m bench.first_scan --smoke                           # CPU: small rig, tiny settings (a smoke test)
    python -m bench.first_scan --scan data/real/capture_0/scan --preset accurate --runs 1   # a scan on disk
    python -m bench.first_scan --preset fast --runs 1 --ops      # each torch op's first call, per source function

One simulated scan (made once, in a process of its own, on the device), or the scan --scan names. Then --runs fresh
processes, one after another, each: the imports, the device's first tensor, the scan loaded, `reconstruct()` twice. The compile and
kernel caches (Warp's kernel cache, Inductor's and Triton's) live in <work>/caches, shared by the runs as a
station's are between commands: with --fresh the first run finds them empty, the next ones warm. `bench/train_speed.py`
times its warm-up inside a process that has already run its microbenchmark; this is the cost a user sees per command.
A second table puts each part of the two scans side by side (the set-up's phases, the first training step, each
extraction stage): what a fresh process pays once shows as the first scan's excess (on CUDA mostly the first launch
of each of torch's kernels, which loads its module: CUDA's lazy loading). With --ops each scan runs under a clock of
torch's ops (a dispatch mode: it slows the scans a little): the host time of the first call of each op and dtypes,
the launch included, where CUDA loads the op's module, and each of Warp's module loads; a third table sums them per
source function of the pipeline, first scan against second, and a fourth lists the costliest first calls.
Writes <out>/<stem>.json and .md (stem default first-scan-<cuda|cpu>[-<preset>]) and prints the table.
"""
from __future__ import annotations

import time

T_START = time.perf_counter()  # the child's clock starts before its imports

import argparse  # noqa: E402
import contextlib  # noqa: E402
import datetime  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
from bench import scan_on_disk, write_study  # noqa: E402
from bench.command_wall import process_env  # noqa: E402  (a fresh process's caches, as a station keeps them)

SMOKE_SET = ["iters=3", "init_iters=2", "mc_resolution=32", "rays=64"]
STAGES = ("setup_s", "train_s", "depth_map_s")


def parts(timings: dict, stages: list[str]) -> dict:
    """{part: s} of one reconstruction's timings: "setup: <phase>" (Trainer.setup_phases), "step 1" (the first
    training step), "extract: <stage>" for each of the extraction's `stages` (their names, in order)."""
    out = {f"setup: {k}": v for k, v in (timings.get("setup_phases_s") or {}).items()}
    if timings.get("first_steps_s"):
        out["step 1"] = timings["first_steps_s"][0]
    out.update({f"extract: {name}": timings[f"{name}_s"] for name in stages if f"{name}_s" in timings})
    return out


class OpClock:
    """Context manager timing, per (torch op, argument dtypes), the host time of its first call while active (the
    launch included: CUDA loads an op's kernel module at its first launch) and where the pipeline made it (the
    innermost frame under slwarp/ or kernels/: 'path:function'); and the time of each of Warp's module loads.
    rows: [{"op", "dtypes", "ms", "at"}] in call order; warp_loads: [{"module", "ms"}]."""

    def __init__(self):
        self.rows, self.warp_loads = [], []

    def __enter__(self):
        import torch
        from torch.utils._python_dispatch import TorchDispatchMode

        clock = self
        seen = set()

        class Mode(TorchDispatchMode):
            def __torch_dispatch__(self, func, types, args=(), kwargs=None):
                kwargs = kwargs or {}
                t = time.perf_counter()
                out = func(*args, **kwargs)
                ms = (time.perf_counter() - t) * 1e3
                dtypes = ",".join(str(a.dtype).removeprefix("torch.") for a in (*args, *kwargs.values())
                                  if isinstance(a, torch.Tensor))
                if (str(func), dtypes) not in seen:
                    seen.add((str(func), dtypes))
                    clock.rows.append({"op": str(func), "dtypes": dtypes, "ms": ms, "at": _pipeline_frame()})
                return out

        self._mode = Mode()
        self._mode.__enter__()
        self._load = _patch_warp_loads(self.warp_loads)
        return self

    def __exit__(self, *exc):
        self._mode.__exit__(*exc)
        if self._load is not None:
            self._load()
        return False


def _pipeline_frame() -> str:
    """'path:function' of the innermost frame of this repository's slwarp/ or kernels/ on the stack ('?': none)."""
    frame = sys._getframe(2)
    while frame is not None:
        path = Path(frame.f_code.co_filename)
        if path.is_relative_to(REPO) and path.relative_to(REPO).parts[0] in ("slwarp", "kernels"):
            return f"{path.relative_to(REPO).as_posix()}:{frame.f_code.co_name}"
        frame = frame.f_back
    return "?"


def _patch_warp_loads(into: list):
    """Time each Warp module load into `into` ({"module", "ms"}); returns the undo, or None where this Warp has no
    such hook (its module class is internal)."""
    try:
        from warp._src.context import Module
    except ImportError:
        return None
    load = Module.load

    def timed(self, *a, **k):
        t = time.perf_counter()
        try:
            return load(self, *a, **k)
        finally:
            into.append({"module": self.name, "ms": (time.perf_counter() - t) * 1e3})

    Module.load = timed

    def undo():
        Module.load = load
    return undo


def op_summary(first: dict, second: dict, top: int = 25) -> dict:
    """The first-use figures of two scans' OpClocks ({"ops", "warp_loads"} each): per source function the summed
    first-call ms of each scan; the `top` costliest first calls of the first scan with the same op's first call in
    the second; the Warp loads' totals."""
    by_where: dict[str, list[float]] = {}
    for i, scan in enumerate((first, second)):
        for row in scan["ops"]:
            by_where.setdefault(row["at"], [0.0, 0.0])[i] += row["ms"]
    again = {(r["op"], r["dtypes"]): r["ms"] for r in second["ops"]}
    costly = sorted(first["ops"], key=lambda r: -r["ms"])[:top]
    return {"by_where": sorted(([k, a, b] for k, (a, b) in by_where.items()), key=lambda x: -(x[1] - x[2])),
            "costliest": [{**r, "second_ms": again.get((r["op"], r["dtypes"]))} for r in costly],
            "ops_ms": [sum(r["ms"] for r in s["ops"]) for s in (first, second)],
            "distinct_ops": [len(s["ops"]) for s in (first, second)],
            "warp_loads_ms": [sum(r["ms"] for r in s["warp_loads"]) for s in (first, second)],
            "warp_loads": [len(s["warp_loads"]) for s in (first, second)]}


def child(args) -> None:
    """One fresh process (see the module docstring); prints one JSON line."""
    import torch

    from slwarp.neural.config import preset
    from slwarp.neural.extraction import build_stages
    from slwarp.neural.reconstruct import reconstruct
    from slwarp.scans.scan import load_scan

    imports = time.perf_counter() - T_START
    cfg = preset(args.preset, **parse_set(args.set)).with_options(device=args.device)
    if args.make:
        from slwarp.sim.simulate import SimOptions, simulate_scene

        simulate_scene(args.scene, "random6", rig=args.rig, options=SimOptions(seed=0), device=args.device).save(args.scan)
        print(json.dumps({"made": str(args.scan)}))
        return
    t = time.perf_counter()
    torch.zeros(1, device=args.device)
    if args.device.startswith("cuda"):
        torch.cuda.synchronize()
    device_start = time.perf_counter() - t
    t = time.perf_counter()
    scan = load_scan(args.scan)
    load = time.perf_counter() - t
    scans, first = [], None
    stages = [stage.name for stage in build_stages(cfg.extraction)]
    clocks = []
    for _ in range(2):
        t = time.perf_counter()
        with OpClock() if args.ops else contextlib.nullcontext() as clock:
            r = reconstruct(scan, cfg, progress=False)
        first = first or time.perf_counter() - T_START
        scans.append({"wall_s": time.perf_counter() - t, **{k: r.timings[k] for k in STAGES},
                      "extract_s": r.timings["depth_map_s"] - r.timings["setup_s"] - r.timings["train_s"],
                      "mae": None if r.metrics is None else r.metrics["mae"], "parts": parts(r.timings, stages)})
        if clock is not None:
            clocks.append({"ops": clock.rows, "warp_loads": clock.warp_loads})
    name = torch.cuda.get_device_name() if args.device.startswith("cuda") else "CPU"
    print(json.dumps({"device": name, "imports_s": imports, "device_start_s": device_start, "load_s": load,
                      "to_first_depth_map_s": first, "scans": scans,
                      **({"first_use": op_summary(*clocks)} if clocks else {})}))


def parse_set(items: list[str]) -> dict:
    from slwarp.neural.config import ConfigError, parse_assignments

    try:
        return parse_assignments(items)
    except ConfigError as e:
        raise SystemExit(f"--set {e}") from None


def run_child(args, extra: list[str], env: dict) -> tuple[dict | None, float, str]:
    """(the child's JSON line, None when it failed or printed none; its wall time from spawn to exit in s; its
    output's last lines)."""
    cmd = [sys.executable, "-m", "bench.first_scan", "--child", "--preset", args.preset, "--scene", args.scene,
           "--rig", args.rig, "--device", args.device, "--scan", str(args.scan), *(["--ops"] if args.ops else []),
           "--set", *args.set, *extra]
    t = time.perf_counter()
    p = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t
    tail = "\n".join((p.stdout + p.stderr).strip().splitlines()[-5:])
    if p.returncode != 0:
        return None, wall, tail
    lines = [ln for ln in p.stdout.splitlines() if ln.startswith("{")]
    return (json.loads(lines[-1]) if lines else None), wall, tail


def markdown(doc: dict) -> str:
    s = doc["setup"]
    lines = [f"# A fresh process's first depth map, preset `{s['preset']}`, {s['scene']} ({s['rig']} rig), "
             f"{doc['device']}, {doc['date']}", "", f"`{doc['bench_command']}`", "",
             "Each run is a fresh process: imports, the device's first tensor, the scan loaded, then `reconstruct()` "
             "twice. 'process to first depth map': from the process's start (after the interpreter's own) to the "
             "first depth map. 'once per process': the first scan's time to the depth map minus the second's. "
             f"Caches ({'Inductor, Triton; Warp kernels in the usual cache' if s['smoke'] else 'Warp kernels, Inductor, Triton'})"
             f" in the work folder{', emptied before run 1' if s['fresh'] else ''}; 'caches' says whether run i found them empty.",
             "", "| run | caches | process wall s | imports s | device start s | process to first depth map s | "
             "first scan: setup / train / extract s | second scan: setup / train / extract s | first / second to "
             "depth map s | once per process s |", "|---|---|---:|---:|---:|---:|---|---|---|---:|"]
    for i, r in enumerate(doc["runs"], 1):
        if r.get("error"):
            why = r["error"][-200:].replace("\n", " / ").replace("|", "\\|")  # one table cell
            lines.append(f"| {i} | {r['caches']} | {r['process_wall_s']:.1f} | failed: {why} |||||||")
            continue
        a, b = r["scans"]
        lines.append(f"| {i} | {r['caches']} | {r['process_wall_s']:.1f} | {r['imports_s']:.2f} | "
                     f"{r['device_start_s']:.2f} | {r['to_first_depth_map_s']:.2f} | "
                     f"{a['setup_s']:.2f} / {a['train_s']:.2f} / {a['extract_s']:.2f} | "
                     f"{b['setup_s']:.2f} / {b['train_s']:.2f} / {b['extract_s']:.2f} | "
                     f"{a['depth_map_s']:.2f} / {b['depth_map_s']:.2f} | {a['depth_map_s'] - b['depth_map_s']:.2f} |")
    return "\n".join(lines + parts_table(doc["runs"]) + first_use_tables(doc["runs"]))


def parts_table(runs: list[dict], floor_s: float = 0.005) -> list[str]:
    """Each part of the first and the second scan (`parts`), means over the runs that finished, the parts that took
    floor_s or more in either; the first scan's excess last."""
    done = [r["scans"] for r in runs if not r.get("error") and "parts" in r["scans"][0]]
    if not done:
        return []
    names = list(dict.fromkeys(k for first, _ in done for k in first["parts"]))
    lines = ["", f"Each part of the two scans, mean of {len(done)} run(s) (s; parts of {floor_s} s or more):", "",
             "| part | first scan | second scan | first - second |", "|---|---:|---:|---:|"]
    for name in names:
        a = sum(first["parts"].get(name, 0.0) for first, _ in done) / len(done)
        b = sum(second["parts"].get(name, 0.0) for _, second in done) / len(done)
        if max(a, b) >= floor_s:
            lines.append(f"| {name} | {a:.3f} | {b:.3f} | {a - b:+.3f} |")
    return lines


def first_use_tables(runs: list[dict], floor_ms: float = 2.0) -> list[str]:
    """With --ops: the first calls of torch's ops per source function (first scan against second, the functions
    whose first scan took floor_ms more), and the costliest first calls, of the last run that has them (with --runs 2
    or more, one whose caches the runs before filled: no kernel compiled in it)."""
    run = next((r for r in reversed(runs) if r.get("first_use")), None)
    if run is None:
        return []
    u = run["first_use"]
    lines = ["", f"First calls of torch's ops (--ops; run {runs.index(run) + 1}): {u['distinct_ops'][0]} / "
             f"{u['distinct_ops'][1]} distinct ops and dtypes, their first calls {u['ops_ms'][0]:.0f} / "
             f"{u['ops_ms'][1]:.0f} ms in the first / second scan; Warp's module loads {u['warp_loads_ms'][0]:.0f} / "
             f"{u['warp_loads_ms'][1]:.0f} ms ({u['warp_loads'][0]} / {u['warp_loads'][1]}). Per source function "
             f"(those whose first scan took {floor_ms:g} ms more):", "",
             "| where | first scan ms | second scan ms | first - second |", "|---|---:|---:|---:|"]
    lines += [f"| {w} | {a:.1f} | {b:.1f} | {a - b:+.1f} |" for w, a, b in u["by_where"] if a - b >= floor_ms]
    lines += ["", "The costliest first calls of the first scan:", "", "| op | dtypes | where | first scan ms | "
              "the op's first call in the second scan ms |", "|---|---|---|---:|---:|"]
    lines += [f"| {r['op']} | {r['dtypes'] or '-'} | {r['at']} | {r['ms']:.1f} | "
              f"{'-' if r['second_ms'] is None else format(r['second_ms'], '.1f')} |" for r in u["costliest"]]
    return lines


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default=None, help="default: the device's default preset (tiny with --smoke)")
    p.add_argument("--scene", default="bunny")
    p.add_argument("--rig", default=None, help="default: default on CUDA, small on the CPU")
    p.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="options applied to the preset")
    p.add_argument("--runs", type=int, default=3, help="fresh processes, one after another")
    p.add_argument("--fresh", action="store_true", help="empty the work folder's caches before the first run")
    p.add_argument("--work", default="/tmp/slwarp-first-scan", help="the scan and the caches")
    p.add_argument("--smoke", action="store_true", help="CPU, small rig, tiny preset and a few iterations")
    p.add_argument("--stem", default=None)
    p.add_argument("--out", default=str(REPO / "bench" / "results"))
    p.add_argument("--device", default=None, help=argparse.SUPPRESS)
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--make", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--scan", default=None, help="a scan folder instead of the simulated scene (e.g. a real capture)")
    p.add_argument("--ops", action="store_true", help="time the first call of each torch op (and Warp's module loads)")
    args = p.parse_args(argv)
    if args.child:
        return child(args)
    if args.runs < 1:
        raise SystemExit("--runs must be >= 1")
    import torch

    cuda = torch.cuda.is_available() and not args.smoke
    args.device = "cuda" if cuda else "cpu"
    if args.smoke:
        args.preset, args.rig, args.scene = args.preset or "tiny", args.rig or "small", "spheres"
        args.set = SMOKE_SET + args.set
    from slwarp.neural.config import default_preset_name

    args.preset = args.preset or default_preset_name(args.device)
    parse_set(args.set)  # a bad option stops here, not in each child
    args.rig = args.rig or ("default" if cuda else "small")
    work = Path(args.work)
    caches, env = process_env(work, args.fresh, args.smoke)
    if args.scan:
        (args.scan, args.scene), args.rig = scan_on_disk(args.scan), "its own"
    else:
        args.scan = work / f"scan-{args.scene}-{args.rig}"
    if args.scan.parent == work and not (args.scan / "scan.yaml").is_file():  # simulated once into the work folder
        # the simulator's kernels in a cache of their own (as bench.command_wall): the caches stay as --fresh left
        # them, and the first run's 'caches' says whether the reconstruction's kernels were there (the smoke test
        # keeps the user's kernel cache for both)
        sim_env = {**env, "SLWARP_KERNEL_CACHE": str(work / "simulator-kernels")} if not args.smoke else env
        made, _, tail = run_child(args, ["--make"], sim_env)
        if made is None:
            raise SystemExit(f"could not simulate the scan into {args.scan}:\n{tail}")
    runs = []
    for i in range(args.runs):
        warm = any(caches.rglob("*"))
        res, wall, tail = run_child(args, [], env)
        row = {"caches": "warm" if warm else "empty", "process_wall_s": wall}
        row.update(res if res is not None else {"error": tail})
        runs.append(row)
        print(f"run {i + 1}: " + (f"{res['to_first_depth_map_s']:.2f} s to the first depth map, the second scan "
                                  f"{res['scans'][1]['depth_map_s']:.2f} s" if res else f"failed:\n{tail}"), flush=True)
    # the device as a child named it (this process never starts CUDA, so it holds no GPU memory meanwhile)
    name = next((r["device"] for r in runs if r.get("device")), "CUDA" if cuda else "CPU")
    doc = {"device": name, "date": str(datetime.date.today()),
           "bench_command": "python -m bench.first_scan " + " ".join(argv if argv is not None else sys.argv[1:]),
           "setup": {"preset": args.preset, "scene": args.scene, "rig": args.rig, "scan": str(args.scan),
                     "set": args.set, "fresh": args.fresh, "smoke": args.smoke, "ops": args.ops}, "runs": runs}
    stem = args.stem or f"first-scan-{'cuda' if cuda else 'cpu'}-{args.preset}"
    write_study(Path(args.out) / stem, doc, lambda d: markdown(d) + "\n")


if __name__ == "__main__":
    main()
