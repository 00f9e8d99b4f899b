"""Batch throughput: scans per hour of `slwarp reconstruct SCANS --out DIR` on one GPU, on G GPUs (torchrun) and
with K scans per GPU at a time; the issue's target is >= 0.9 x G scaling over G GPUs.

    python -m bench.batch_throughput                          # every visible GPU: 8 scans, paper preset
    python -m bench.batch_throughput --configs 1x1,4x1 --time-limit 540 --set iters=1000
    python -m bench.batch_throughput --smoke                  # CPU: 3 small scans, tiny settings (a smoke test)

A configuration GxK[:launcher] runs the batch on G GPUs with K scans per GPU at a time:
- 1x1: one process, one scan after another (`slwarp reconstruct DIR --per-device 0`);
- 1xK: K worker processes on one GPU (`--per-device K`: how a single-GPU user fills a big GPU);
- GxK with G > 1: `torchrun --standalone --nproc-per-node G*K`; GPU LOCAL_RANK % G.
`:torchrun` or `:per-device` picks the other launcher; `Gx1:plain` runs the command as a user types it, no launcher
flag (`slwarp reconstruct DIR` on G GPUs: the command picks how many scans a GPU runs at a time). Default configurations: 1x1, 1xK, Gx1, GxK for every K of
--per-gpu (G = --gpus, default all visible GPUs).

The scans: --scans simulated scans (default rig, 6 random patterns, scenes in turn, a noise seed each), made once
in the work folder and reused. Before the configurations, a short warm-up run fills the Warp kernel cache that
every configuration shares (a station's cache is warm). torch.compile's caches (TORCHINDUCTOR_CACHE_DIR,
TRITON_CACHE_DIR): with --compile-cache warm (default) the warm-up fills them too and every configuration shares
them, as a station's persist between runs; with cold each configuration starts them empty. Either way each process
compiles (or loads) the training graphs for its first scan and reuses them for the next scans of the same sizes
(slwarp.batch).

Each configuration is one command with its own time limit (--time-limit; the process group is stopped after it):
its throughput is the scans completed over the command's wall time (process start-up included), per hour, so a
configuration cut short still gives one; a configuration that fails is recorded with its log's last lines and
the others go on. Python's bytecode: `--bytecode warm` (default) compiles the installed packages into
<work>/pycache first (PYTHONPYCACHEPREFIX), as a user's machine, which keeps its bytecode caches, has them (the lent
GPU machines have none, and each process there compiled torch from source: seconds per process); `as-is` leaves
it as the machine has it. Results go to <out>/batch-throughput-<cuda|cpu>.json and .md; a later call with the same
scans and settings adds its configurations to them (so that each configuration can run in its own call).
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SCENES = ("bunny", "vase", "spheres", "torus")
TARGET_EFFICIENCY = 0.9  # the target: >= 0.9 x G scaling over G GPUs
SMOKE = dict(scans=3, scenes="spheres", rig="small", preset="tiny",
             set=["iters=10", "init=sphere", "mc_resolution=32", "backend=torch", "depth_method=sphere"],
             configs="1x1,1x2,1x2:torchrun", gpus=1, time_limit=600.0)


# ----------------------------------------------------------------------------------------------
# scans and device (in a subprocess of their own, so that this process never holds a GPU)


def prepare(spec: dict) -> dict:
    """Simulate the scans `spec` asks for into spec['dir'] (those already there are kept) and describe the
    device: {"device": name, "gpus": count, "scans": [folders]}."""
    import torch

    from slwarp.sim.simulate import SimOptions, simulate_scene

    cuda = torch.cuda.is_available() and not spec["cpu"]
    folder = Path(spec["dir"])
    made = []
    for i in range(spec["scans"]):
        scene = spec["scenes"][i % len(spec["scenes"])]
        path = folder / f"{i:02d}-{scene}"
        if not (path / "scan.yaml").is_file():
            scan = simulate_scene(scene, spec["patterns"], rig=spec["rig"], options=SimOptions(seed=i),
                                  device="cuda" if cuda else "cpu")
            scan.save(path)
        made.append(str(path))
    name = torch.cuda.get_device_name(0) if cuda else f"CPU ({os.cpu_count()} cores)"
    return {"device": name, "gpus": torch.cuda.device_count() if cuda else 0, "scans": made}


# ----------------------------------------------------------------------------------------------
# configurations


def parse_config(token: str, unit: str) -> dict:
    """'GxK[:launcher]' -> {name, gpus, per_gpu, launcher} (see the module docstring)."""
    body, _, launcher = token.partition(":")
    try:
        g, _, k = body.partition("x")
        gpus, per_gpu = int(g), int(k or 1)
    except ValueError:
        raise SystemExit(f"--configs: {token!r} is not GxK[:launcher], e.g. 1x1, 1x2, 4x1, 4x2:per-device") from None
    if gpus < 1 or per_gpu < 1:
        raise SystemExit(f"--configs: {token!r}: G and K must be >= 1")
    default = "sequential" if gpus == per_gpu == 1 else "per-device" if gpus == 1 else "torchrun"
    launcher = launcher or default
    if launcher not in ("sequential", "per-device", "torchrun", "plain"):
        raise SystemExit(f"--configs: {token!r}: the launcher is sequential, per-device, torchrun or plain")
    if launcher == "plain" and per_gpu != 1:
        raise SystemExit(f"--configs: {token!r}: the plain command picks its scans a GPU itself (write Gx1:plain)")
    if launcher == "sequential" and gpus * per_gpu != 1:
        raise SystemExit(f"--configs: {token!r}: one process runs one scan at a time on one device")
    name = f"{gpus}{unit}" + (f"-x{per_gpu}" if per_gpu > 1 else "") + ("" if launcher == default else f"-{launcher}")
    return {"name": name, "token": token, "gpus": gpus, "per_gpu": per_gpu, "launcher": launcher}


def default_configs(gpus: int, per_gpu: list[int]) -> list[str]:
    tokens = ["1x1"] + [f"1x{k}" for k in per_gpu]
    if gpus > 1:
        tokens += [f"{gpus}x1"] + [f"{gpus}x{k}" for k in per_gpu]
    return list(dict.fromkeys(tokens))


def command(cfg: dict, scans_dir: Path, out: Path, reconstruct_args: list[str]) -> list[str]:
    slwarp = ["-m", "slwarp", "reconstruct", str(scans_dir), "--out", str(out), "--quiet", *reconstruct_args]
    if cfg["launcher"] == "torchrun":
        return [sys.executable, "-m", "torch.distributed.run", "--standalone",
                "--nproc-per-node", str(cfg["gpus"] * cfg["per_gpu"]), *slwarp]
    if cfg["launcher"] == "per-device":
        return [sys.executable, *slwarp, "--per-device", str(cfg["per_gpu"])]
    if cfg["launcher"] == "plain":
        return [sys.executable, *slwarp]
    return [sys.executable, *slwarp, "--per-device", "0"]  # one after another in one process (else 2 a GPU)


def visible_gpus() -> list[str]:
    """The CUDA device ids this process may hand to a configuration (CUDA_VISIBLE_DEVICES, else 0..N-1)."""
    given = os.environ.get("CUDA_VISIBLE_DEVICES")
    if given:
        return [d for d in given.split(",") if d.strip()]
    try:
        out = subprocess.run(["nvidia-smi", "--query-gpu=index", "--format=csv,noheader"], capture_output=True,
                             text=True, timeout=60)
        return [line.strip() for line in out.stdout.splitlines() if line.strip()]
    except (OSError, subprocess.SubprocessError):
        return []


def compile_cache_env(folder: Path) -> dict:
    """The environment that puts torch.compile's caches (inductor's and Triton's) in `folder`."""
    return {"TORCHINDUCTOR_CACHE_DIR": str(folder / "cache-inductor"), "TRITON_CACHE_DIR": str(folder / "cache-triton")}


def run_config(cfg: dict, scans_dir: Path, work: Path, reconstruct_args: list[str], gpu_ids: list[str], cpu: bool,
               time_limit: float, kernel_cache: Path, compile_cache: str = "warm", base_env: dict | None = None) -> dict:
    """Run one configuration as its own command (process group), at most `time_limit` s; its numbers.
    compile_cache "warm": torch.compile's caches of the work folder (the warm-up's); "cold": fresh ones.
    base_env: the environment to start from (default this process's)."""
    from slwarp.batch import outputs_complete

    out = work / cfg["name"]
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    env = {**(base_env or os.environ), "PYTHONUNBUFFERED": "1", "SLWARP_KERNEL_CACHE": str(kernel_cache),
           "SLWARP_TIMELINE": str(work / f"{cfg['name']}.timeline.jsonl"),
           **compile_cache_env(work if compile_cache == "warm" else out)}
    if not cpu:
        env["CUDA_VISIBLE_DEVICES"] = ",".join(gpu_ids[: cfg["gpus"]])
    cmd = command(cfg, scans_dir, out / "outputs", reconstruct_args)
    log_path = work / f"{cfg['name']}.log"
    print(f"[{cfg['name']}] {' '.join(cmd)}", flush=True)
    timeline_path = Path(env["SLWARP_TIMELINE"])
    timeline_path.unlink(missing_ok=True)
    spawned = time.time()
    t0 = time.perf_counter()
    with open(log_path, "w") as log:
        proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            rc, timed_out = proc.wait(timeout=time_limit), False
        except subprocess.TimeoutExpired:
            timed_out = True
            os.killpg(proc.pid, signal.SIGTERM)  # the launcher and every worker it started
            try:
                proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
            rc = proc.returncode
    wall = time.perf_counter() - t0
    outputs = out / "outputs"
    completed = sum(outputs_complete(d) for d in outputs.iterdir()) if outputs.is_dir() else 0
    row = {**cfg, "command": " ".join(cmd), "returncode": rc, "timed_out": timed_out, "wall_s": wall,
           "completed": completed, "scans_per_hour": completed / wall * 3600.0 if wall > 0 else 0.0}
    summary = outputs / "summary.json"
    if summary.is_file():
        doc = json.loads(summary.read_text())
        t = doc["totals"]
        done = [s for s in doc["scans"] if s["status"] == "done"]
        row.update(done=t["done"], failed=t["failed"], batch_wall_s=t["wall_s"], mean_mae=t["mean_mae"],
                   mean_scan_s=sum(s["seconds"] for s in done) / len(done) if done else None,
                   errors=sorted({s["error"] for s in doc["scans"] if s["error"]}), stages=stage_means(done))
    row["first_scan_done_s"] = first_scans(timeline_path, spawned)
    if timed_out or summary.is_file() is False or rc != 0:  # 1: failed scans, or a launcher's own failure
        row["log_tail"] = log_path.read_text()[-2000:]
    print(f"[{cfg['name']}] {completed} scans in {wall:.1f} s: {row['scans_per_hour']:.1f} scans/h"
          + (" (time limit)" if timed_out else "") + (f"; exit status {rc}" if rc else ""), flush=True)
    return row


def first_scans(path: Path, spawned: float) -> list[float] | None:
    """Seconds from the command's spawn to each process's first finished scan (its 'scan 1' mark, slwarp.timeline),
    earliest first: the start-up a batch pays before its GPUs are all busy. None without marks."""
    if not path.is_file():
        return None
    done = []
    for line in path.read_text().splitlines():
        marks = dict(json.loads(line)["marks"])
        if "scan 1" in marks:
            done.append(marks["scan 1"] - spawned)
    return sorted(done) or None


STAGES = ("setup", "train", "extract", "other")  # the columns of stage_means


def stage_means(done: list[dict]) -> dict | None:
    """Where the done scans' time went, mean s per scan, from each scan's timings.json: setup (search, blur fit,
    field), train, extract (the rest up to the depth map), other (loading the scan, writing the outputs, the
    metrics: the scan's wall time less reconstruct's); a process's first scan compiles (or loads) the training
    graphs in its first steps (train). Why: when scans on several GPUs take longer each than one after another,
    this says which part grew."""
    rows = []
    for s in done:
        path = Path(s["out_dir"]) / "timings.json"
        if not path.is_file():
            continue
        t = json.loads(path.read_text())
        if not all(k in t for k in ("setup_s", "train_s", "depth_map_s", "total_s")):
            continue
        rows.append(dict(setup=t["setup_s"], train=t["train_s"], extract=t["depth_map_s"] - t["setup_s"] - t["train_s"],
                         other=s["seconds"] - t["total_s"]))
    return {k: sum(r[k] for r in rows) / len(rows) for k in STAGES} if rows else None


# ----------------------------------------------------------------------------------------------
# results


def add_scaling(rows: list[dict]) -> None:
    """Speed-up against 1x1, and scaling efficiency against one GPU at the same K (speed-up / G)."""
    by_token = {(r["gpus"], r["per_gpu"]): r for r in rows if r["launcher"] != "torchrun" or r["gpus"] > 1}
    base = by_token.get((1, 1))
    for r in rows:
        one = by_token.get((1, r["per_gpu"]))
        r["vs_1x1"] = r["scans_per_hour"] / base["scans_per_hour"] if base and base["scans_per_hour"] else None
        r["efficiency"] = (r["scans_per_hour"] / one["scans_per_hour"] / r["gpus"]
                           if one and one["scans_per_hour"] and r["gpus"] > 1 else None)


def markdown(doc: dict) -> str:
    s = doc["setup"]
    unit = "CPU" if s["cpu"] else "GPU"
    lines = [f"# Batch throughput, {doc['device']}, {doc['date']}", ""]
    calls = doc.get("bench_commands") or ([doc["bench_command"]] if doc.get("bench_command") else [])
    if len(calls) > 1:
        lines += ["Configurations from these calls, one after another on the same machine:", "",
                  *[f"    {c}" for c in calls], ""]
    elif calls:
        lines += [f"`{calls[0]}`", ""]
    if s.get("smoke"):
        lines += ["Smoke test (`--smoke`): tiny settings that check the commands run; the numbers say nothing of the "
                  "throughput of real scans.", ""]
    lines += [f"{s['scans']} scans ({s['rig']} rig, {s['patterns']}, scenes {', '.join(s['scenes'])}), preset "
             f"`{s['preset']}`" + (f" with {', '.join(s['set'])}" if s["set"] else "") + f"; {doc['gpus']} {unit}(s) "
             "visible. Throughput: scans completed over the command's wall time (start-up included). "
             f"Efficiency: throughput over {unit.lower()}s x that of one {unit.lower()} at the same scans per "
             f"{unit.lower()} (target >= {TARGET_EFFICIENCY}). torch.compile's caches: "
             + ("filled by the warm-up and shared (as a station's)" if s.get("compile_cache", "cold") == "warm"
                else "empty at the start of each configuration") + ". Python's bytecode: "
             + ("compiled first, as a user's machine keeps it" if s.get("bytecode") == "warm" else "as the machine had it")
             + ".", "",
             f"| configuration | {unit}s | scans per {unit} | launcher | done / failed | wall s | scans/h | vs 1x1 | "
             "efficiency | mean s per scan | first scans done s | mean MAE mm |",
             "|---|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|"]

    def f(v, fmt):
        return "-" if v is None else fmt.format(v)

    def first_done(times):  # per process: the first to finish its first scan and the last
        if not times:
            return "-"
        return f"{times[0]:.1f}" if len(times) == 1 else f"{times[0]:.1f}-{times[-1]:.1f}"

    for r in doc["configs"]:
        state = f"{r.get('done', r['completed'])} / {r.get('failed', '-')}" + (" (time limit)" if r["timed_out"] else "")
        lines.append(f"| {r['name']} | {r['gpus']} | {r['per_gpu']} | {r['launcher']} | {state} | {r['wall_s']:.1f} | "
                     f"{r['scans_per_hour']:.1f} | {f(r.get('vs_1x1'), '{:.2f}x')} | {f(r.get('efficiency'), '{:.2f}')} | "
                     f"{f(r.get('mean_scan_s'), '{:.1f}')} | {first_done(r.get('first_scan_done_s'))} | "
                     f"{f(r.get('mean_mae'), '{:.3f}')} |")
    lines.append("")
    staged = [r for r in doc["configs"] if r.get("stages")]
    if staged:
        lines += ["Where a scan's time went (mean s per scan; `other`: loading, outputs, metrics):", "",
                  "| configuration | " + " | ".join(STAGES) + " |", "|---|" + "---:|" * len(STAGES)]
        for r in staged:
            lines.append(f"| {r['name']} | " + " | ".join(f(r["stages"].get(k), "{:.2f}") for k in STAGES) + " |")
        lines.append("")
    one_k = [r for r in doc["configs"] if r["gpus"] == 1 and r["scans_per_hour"] > 0]
    if one_k:
        best = max(one_k, key=lambda r: r["scans_per_hour"])
        lines.append(f"Best on one {unit.lower()}: {best['per_gpu']} scan(s) at a time ({best['name']}, "
                     f"{best['scans_per_hour']:.1f} scans/h).")
    for r in doc["configs"]:
        if r.get("efficiency") is not None:
            verdict = "meets" if r["efficiency"] >= TARGET_EFFICIENCY else "misses"
            lines.append(f"{r['name']}: {r['efficiency']:.2f} x {r['gpus']} scaling over {r['gpus']} {unit.lower()}s "
                         f"({verdict} the {TARGET_EFFICIENCY} target).")
    for r in doc["configs"]:
        if r.get("errors"):
            lines.append(f"{r['name']}: scan errors: {'; '.join(r['errors'])}")
        if r["returncode"] not in (0, 1) and not r["timed_out"]:
            lines.append(f"{r['name']}: the command failed (exit status {r['returncode']}); see the JSON's log_tail.")
    lines += ["", "Commands:", "", *[f"    {r['command']}" for r in doc["configs"]], ""]
    return "\n".join(lines)


def reconstruct_flags(preset: str, device: str, options: list[str]) -> list[str]:
    """The reconstruct command's flags for a preset, a device and --set's OPTION=VALUE items (booleans as --key /
    --no-key, as bench.command_wall gives them)."""
    from bench.command_wall import option_flags  # imported here: bench.command_wall imports this module

    return ["--preset", preset, "--device", device, *option_flags(options)]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scans", type=int, default=8, help="simulated scans in the batch (default 8)")
    p.add_argument("--scenes", default=",".join(SCENES), help="scenes, in turn (default %(default)s)")
    p.add_argument("--rig", default="default", help="rig of the simulated scans (default %(default)s)")
    p.add_argument("--patterns", default="random6", help="pattern set (default %(default)s)")
    p.add_argument("--preset", default=None, help="training preset (default: paper on CUDA, tiny with --smoke)")
    p.add_argument("--set", action="append", default=[], metavar="OPTION=VALUE",
                   help="a TrainConfig option for every scan (repeatable), e.g. iters=1000")
    p.add_argument("--gpus", type=int, default=None, help="GPUs for the multi-GPU configurations (default: all visible)")
    p.add_argument("--per-gpu", default="2", help="K values of the default configurations (default 2)")
    p.add_argument("--configs", default=None, help="comma-separated GxK[:launcher] (see above)")
    p.add_argument("--time-limit", type=float, default=1800.0, help="seconds per configuration (default 1800)")
    p.add_argument("--work", default="/tmp/slwarp-batch-bench", help="scans, outputs, logs and caches (default %(default)s)")
    p.add_argument("--out", default=str(REPO / "bench" / "results"), help="results folder (default bench/results)")
    p.add_argument("--no-warmup", action="store_true", help="skip the warm-up run that fills the Warp kernel cache")
    p.add_argument("--compile-cache", choices=["warm", "cold"], default="warm",
                   help="torch.compile's caches: warm (filled by the warm-up, shared, as a station's) or cold (empty "
                        "in each configuration); default %(default)s")
    p.add_argument("--bytecode", choices=["warm", "as-is"], default="warm",
                   help="Python's bytecode: compiled into <work>/pycache first, as a user's machine has it (warm, "
                        "default), or as this machine has it (as-is)")
    p.add_argument("--smoke", action="store_true", help="CPU smoke test: " + ", ".join(f"{k} {v}" for k, v in SMOKE.items()))
    p.add_argument("--cpu", action="store_true", help="run on the CPU even when CUDA is present")
    p.add_argument("--_prepare", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args._prepare:
        print(json.dumps(prepare(json.loads(args._prepare))))
        return 0
    if args.smoke:
        for key, value in SMOKE.items():
            if key == "set":
                args.set = value + args.set
            elif key == "gpus" or p.get_default(key) == getattr(args, key):
                setattr(args, key, value)
        args.cpu = True
    scenes = [s for s in args.scenes.split(",") if s]
    work = Path(args.work)
    scans_dir = work / f"scans-{args.rig}-{args.patterns}-{'-'.join(scenes)}"
    spec = {"dir": str(scans_dir), "scans": args.scans, "scenes": scenes, "rig": args.rig, "patterns": args.patterns,
            "cpu": args.cpu}
    print(f"preparing {args.scans} scans in {scans_dir} ...", flush=True)
    base_env = dict(os.environ)
    bytecode_s = None
    if args.bytecode == "warm":
        from bench.command_wall import compile_bytecode

        base_env["PYTHONPYCACHEPREFIX"] = str(work / "pycache")
        bytecode_s = compile_bytecode(work / "pycache")
        print(f"bytecode compiled into {work / 'pycache'} in {bytecode_s:.1f} s", flush=True)
    kernel_cache = work / "kernel-cache"
    prep = subprocess.run([sys.executable, __file__, "--_prepare", json.dumps(spec)], capture_output=True, text=True,
                          env={**os.environ, "SLWARP_KERNEL_CACHE": str(kernel_cache)})
    if prep.returncode != 0:
        print(prep.stdout[-3000:] + prep.stderr[-3000:], file=sys.stderr)
        return 1
    info = json.loads(prep.stdout.strip().splitlines()[-1])
    cpu = args.cpu or info["gpus"] == 0
    extra = [p for p in scans_dir.iterdir() if p.is_dir() and str(p) not in info["scans"]]
    for path in extra:  # scans left by an earlier call with more --scans: the batch is exactly these
        shutil.rmtree(path)
    gpu_ids = [] if cpu else visible_gpus()[: info["gpus"]]
    gpus = 1 if cpu else (args.gpus or len(gpu_ids))
    unit = "cpu" if cpu else "gpu"
    per_gpu = [int(k) for k in args.per_gpu.split(",") if k]
    tokens = args.configs.split(",") if args.configs else default_configs(gpus, per_gpu)
    configs = [parse_config(t, unit) for t in tokens]
    for c in configs:
        if not cpu and c["gpus"] > len(gpu_ids):
            raise SystemExit(f"--configs: {c['token']} needs {c['gpus']} GPUs, {len(gpu_ids)} visible")
    preset = args.preset or ("tiny" if cpu else "paper")
    device = "cpu" if cpu else "cuda"
    reconstruct_args = reconstruct_flags(preset, device, args.set)
    if not args.no_warmup:
        first = info["scans"][0]
        warm = [sys.executable, "-m", "slwarp", "reconstruct", first, "--out", str(work / "warmup"), "--quiet",
                *reconstruct_args, "--iters", "20", "--init-iters", "10"]
        shutil.rmtree(work / "warmup", ignore_errors=True)
        t0 = time.perf_counter()
        w = subprocess.run(warm, cwd=REPO, env={**base_env, "SLWARP_KERNEL_CACHE": str(kernel_cache),
                                                 **(compile_cache_env(work) if args.compile_cache == "warm" else {}),
                                                 **({} if cpu else {"CUDA_VISIBLE_DEVICES": gpu_ids[0]})},
                           capture_output=True, text=True)
        print(f"warm-up: {time.perf_counter() - t0:.1f} s" + (f" (failed: {w.stderr.strip()[-500:]})" if w.returncode else ""),
              flush=True)
    setup = {"cpu": cpu, "device": info["device"], "scans": args.scans, "scenes": scenes, "rig": args.rig,
             "patterns": args.patterns, "preset": preset, "set": args.set, "smoke": args.smoke,
             "compile_cache": args.compile_cache, "bytecode": args.bytecode}
    rows = []
    for c in configs:
        try:
            rows.append(run_config(c, scans_dir, work, reconstruct_args, gpu_ids, cpu, args.time_limit, kernel_cache,
                                   args.compile_cache, base_env))
        except Exception as e:  # a configuration that cannot even start: recorded, the others go on
            rows.append({**c, "command": "", "returncode": None, "timed_out": False, "wall_s": 0.0, "completed": 0,
                         "scans_per_hour": 0.0, "errors": [f"{type(e).__name__}: {e}"]})
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"batch-throughput-{'cpu' if cpu else 'cuda'}.json"
    command_line = " ".join(["python -m bench.batch_throughput", *(sys.argv[1:] if argv is None else argv)])
    commands = [command_line]
    if path.is_file():  # same scans and settings: keep the configurations this call did not run
        old = json.loads(path.read_text())
        if old.get("setup") == setup:
            names = {r["name"] for r in rows}
            rows = [r for r in old["configs"] if r["name"] not in names] + rows
            commands = old.get("bench_commands", [old.get("bench_command")]) + commands
    order = {(r["gpus"], r["per_gpu"], r["launcher"]): i for i, r in enumerate(rows)}
    rows.sort(key=lambda r: (r["gpus"], r["per_gpu"], order[(r["gpus"], r["per_gpu"], r["launcher"])]))
    add_scaling(rows)
    doc = {"device": info["device"], "gpus": gpus if not cpu else 1, "date": datetime.date.today().isoformat(),
           "setup": setup, "configs": rows, "bytecode_s": bytecode_s,
           "bench_command": command_line, "bench_commands": [c for c in commands if c]}
    path.write_text(json.dumps(doc, indent=1) + "\n")
    text = markdown(doc)
    path.with_suffix(".md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
