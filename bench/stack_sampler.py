"""Where a fresh command's main thread spends its wall time: a stack sampler, and its report per phase.

    python -m bench.stack_sampler FOLDER -m slwarp reconstruct SCAN ...   # run a command under the sampler
    python -m bench.command_wall --preset fast --sample                    # how it is used: each run sampled

Every --interval ms (default 2; $SLWARP_SAMPLE_MS) a thread records the main thread's stack (sys._current_frames) with
the wall clock. A forked child (`slwarp reconstruct` forks: slwarp.cli.loader) samples itself from the fork on. Each
process writes its samples to FOLDER/<pid>.json.gz when it ends (os._exit, as the command ends) or at the
interpreter's exit. Why not cProfile: it counts the calls of the profiled thread only, and a native call that holds
the interpreter lock (CUDA's driver start inside torch, NVML's) shows up as a gap here, where cProfile gave its time
to other frames. The sampler itself costs the main thread a few per cent.

`report(samples, marks, timings)` attributes each interval between two samples to the earlier sample's stack: per
phase (the command's timeline marks and timings.json, as bench.command_wall splits them) the places (the innermost
frame of this project, and the innermost frame) where the main thread was longest, and the intervals above
`gap_ms`: the main thread held the lock in one call that long (the frames before and after it name the call).
"""
from __future__ import annotations

import atexit
import collections
import gzip
import json
import os
import runpy
import sys
import threading
import time
from pathlib import Path

OURS = ("slwarp/", "kernels/", "bench/")


def _frame_name(code, line: int) -> str:
    path = code.co_filename
    for marker in ("site-packages/", "/slwarp/", "/kernels/", "/bench/"):
        if marker in path:
            tail = path.split(marker, 1)[1]
            path = (marker.strip("/") + "/" + tail) if marker != "site-packages/" else tail
            break
    return f"{path}:{code.co_name}:{line}"


class Sampler:
    """Samples the main thread's stack every `interval_s` into `samples` ([(wall time, [frame, ...] innermost
    first)]) until the process ends; `dump(folder)` writes them."""

    def __init__(self, interval_s: float):
        self.interval_s = interval_s
        self.samples: list = []
        self._main = threading.main_thread().ident
        self.start()

    def start(self) -> None:
        threading.Thread(target=self._run, name="stack-sampler", daemon=True).start()

    def _run(self) -> None:
        while True:
            time.sleep(self.interval_s)
            frame = sys._current_frames().get(self._main)
            stack = []
            while frame is not None and len(stack) < 80:
                stack.append(_frame_name(frame.f_code, frame.f_lineno))
                frame = frame.f_back
            self.samples.append((time.time(), stack))

    def after_fork(self) -> None:
        """In a forked child: its own samples from here on (the thread did not survive the fork)."""
        self._main = threading.main_thread().ident
        self.samples = []
        self.start()

    def dump(self, folder: Path) -> None:
        if not self.samples:
            return
        tmp = folder / f".{os.getpid()}.json.gz"
        with gzip.open(tmp, "wt") as f:
            json.dump(list(self.samples), f)
        os.replace(tmp, folder / f"{os.getpid()}.json.gz")  # whole or absent for the reader


def run(folder: Path, argv: list[str], interval_s: float) -> None:
    """Run `python -m MODULE ARGS` (argv: ["-m", MODULE, ARGS...]) in this process under a Sampler."""
    if len(argv) < 2 or argv[0] != "-m":
        raise SystemExit("usage: python -m bench.stack_sampler FOLDER -m MODULE [ARGS...]")
    folder.mkdir(parents=True, exist_ok=True)
    sampler = Sampler(interval_s)
    os.register_at_fork(after_in_child=sampler.after_fork)
    real_exit = os._exit

    def exit_with_samples(code):
        sampler.dump(folder)
        real_exit(code)

    os._exit = exit_with_samples
    atexit.register(sampler.dump, folder)
    sys.argv = [argv[1], *argv[2:]]
    runpy.run_module(argv[1], run_name="__main__", alter_sys=True)


def load(folder: Path, pid: int, wait_s: float = 30.0) -> list:
    """The samples process `pid` wrote into `folder` (waiting up to wait_s for them: a forked child writes its own
    after its parent, the command, has returned)."""
    path = folder / f"{pid}.json.gz"
    deadline = time.time() + wait_s
    while not path.is_file() and time.time() < deadline:
        time.sleep(0.1)
    if not path.is_file():
        return []
    with gzip.open(path, "rt") as f:
        return json.load(f)


def _ours(stack: list[str]) -> str:
    for frame in stack:
        if frame.startswith(OURS) and not frame.startswith("bench/stack_sampler"):
            return frame.rsplit(":", 1)[0]
    return "-"


def _short(frame: str) -> str:
    path, name, line = frame.rsplit(":", 2)
    return f"{path.rsplit('/', 1)[-1]}:{name}:{line}"


def phase_windows(marks: dict, timings: dict) -> list[tuple[str, float, float]]:
    """(phase, start, end) in wall-clock seconds from the command's timeline marks and its timings.json."""
    r = marks["reconstruct"]
    s, t, d = timings["setup_s"], timings["train_s"], timings["depth_map_s"]
    edges = [("interpreter and imports", marks["started"], marks["imports"]),
             ("scan", marks["imports"], marks["scan loaded"]), ("to reconstruct()", marks["scan loaded"], r),
             ("setup", r, r + s), ("training", r + s, r + s + t), ("extraction", r + s + t, r + d),
             ("metrics, outputs", r + d, marks["reconstructed"]), ("report", marks["reconstructed"], marks["exit"])]
    return [(name, a, b) for name, a, b in edges if b > a]


def report(samples: list, marks: dict, timings: dict, top: int = 4, gap_ms: float = 25.0) -> dict:
    """{"phases": [{phase, seconds, places: [[place, seconds], ...]}], "gaps": [{at_s, ms, phase, before, after}]}:
    each interval between two samples given to the earlier sample's stack; places are "our innermost frame <
    innermost frame"; times from the command's start (mark "started")."""
    windows = phase_windows(marks, timings)
    t0 = marks["started"]

    def phase_of(t: float) -> str:
        for name, a, b in windows:
            if a <= t < b:
                return name
        return "outside"

    per = collections.defaultdict(collections.Counter)
    gaps = []
    for (t, stack), (t2, after) in zip(samples, samples[1:]):
        if not stack:
            continue
        name, dt = phase_of(t), t2 - t
        per[name][f"{_ours(stack)} < {_short(stack[0])}"] += dt
        if dt * 1000 >= gap_ms:
            gaps.append({"at_s": round(t - t0, 3), "ms": round(dt * 1000, 1), "phase": name,
                         "before": [_short(f) for f in stack[:4]], "after": [_short(f) for f in after[:4]]})
    phases = [{"phase": name, "seconds": round(b - a, 3),
               "places": [[p, round(v, 3)] for p, v in per[name].most_common(top)]} for name, a, b in windows]
    return {"phases": phases, "gaps": sorted(gaps, key=lambda g: -g["ms"])}


def markdown(rep: dict, title: str, gaps: int = 10) -> list[str]:
    """The report as markdown lines: the places per phase, then the longest lock-held intervals."""
    lines = [f"### {title}", "", "| phase | s | where the main thread was (our innermost frame < innermost frame: s) |",
             "|---|---:|---|"]
    for p in rep["phases"]:
        places = "; ".join(f"`{place}`: {s:.3f}" for place, s in p["places"])
        lines.append(f"| {p['phase']} | {p['seconds']:.2f} | {places} |")
    if rep["gaps"]:
        lines += ["", "The longest intervals between two samples (the main thread held the interpreter lock in one "
                  "call; the frames before and after name it):", "", "| at s | ms | phase | before | after |",
                  "|---:|---:|---|---|---|"]
        for g in rep["gaps"][:gaps]:
            lines.append(f"| {g['at_s']:.2f} | {g['ms']:.0f} | {g['phase']} | `{' < '.join(g['before'][:2])}` | "
                         f"`{' < '.join(g['after'][:2])}` |")
    return lines


if __name__ == "__main__":
    if len(sys.argv) < 2:
        raise SystemExit("usage: python -m bench.stack_sampler FOLDER -m MODULE [ARGS...]")
    run(Path(sys.argv[1]), sys.argv[2:], float(os.environ.get("SLWARP_SAMPLE_MS", "2")) / 1000.0)
