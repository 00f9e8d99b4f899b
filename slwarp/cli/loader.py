"""`slwarp reconstruct SCAN` as two processes: the scan is loaded beside the command's imports, and the command
returns once its files are written, not once the GPU's runtimes are torn down.

    ahead = load_beside(args)    # in the command's process: forks; None where it does not (see `splits`)
    ...                          # here only the child goes on: imports torch, Warp, the reconstruction
    scan = ahead.scan()          # the Scan the parent loaded (its camera's ray grid cached too), or its error
    ...
    report_exit(code)            # entry(): the parent, waiting on the user's prompt, exits with `code` now

The process the user started forks before it imports anything heavy. The child runs the command as always; the
parent loads the scan (decoding its PNG frames) and undistorts the camera's ray grid meanwhile, on other cores
and under its own interpreter lock (loading it in a thread of the importing process made both slower: imports 2.0
-> 2.4-3.2 s, H100 host), and sends both through a pipe that a thread of the child drains during its imports (a
pipe's read leaves the lock free). Then the parent waits: when the child has written and flushed every file it
reports its exit status and the parent exits with it, while the child's runtimes (CUDA's context, Warp, torch)
tear down after the prompt is back (0.2-0.3 s of a fresh command on an H100 host). A pipe reading the command's
output sees its end at the same moment: the child hands its standard streams back first.

Ctrl-C reaches both processes (one process group): the child stops as it would alone (a checkpoint kept, status
130) and the parent exits with the child's status. A SIGTERM sent to the parent alone is passed on to the child, and
a parent killed outright (SIGKILL) leaves the child a SIGTERM. Where the child dies without a status (a crash,
SIGKILL), the parent exits with the status the child's end gives.
"""
from __future__ import annotations

import os
import pickle
import signal
import struct
import sys
import threading

# the pipe's messages: a header (meta bytes, buffer count) then the pickle's out-of-band buffers, each with its size
_HEADER = struct.Struct("<QQ")
_SIZE = struct.Struct("<Q")
_STATUS = struct.Struct("<i")

_may_fork = False  # set by entry(): only the `slwarp` command forks, never a caller of main() (tests, the API)
_report_fd: int | None = None  # the child's end of the pipe its exit status goes through


def allow_fork() -> None:
    """Let this process's single-scan `reconstruct` split into the two processes (entry() calls this)."""
    global _may_fork
    _may_fork = True


def splits(args):
    """The scans found (batch.find_scans' Discovery) when `reconstruct` with these arguments loads its scan in a
    process of its own, else None: the `slwarp` command (allow_fork), Linux (where the GPUs are; macOS's system
    libraries are not safe to fork), one scan folder (not a batch), no --per-device, not a torchrun rank, and
    $SLWARP_LOADER not 0."""
    from ..batch.discovery import find_scans
    from ..batch.launch import launched_by_torchrun

    if not _may_fork or not sys.platform.startswith("linux") or os.environ.get("SLWARP_LOADER", "1") == "0":
        return None
    if args.per_device is not None or launched_by_torchrun():
        return None
    try:
        found = find_scans(args.scans)
    except Exception:  # noqa: BLE001 - the command reports a bad scan word itself, in its order
        return None
    return found if found.single else None


def load_beside(args):
    """Fork when `splits(args)`: returns a ScanAhead in the child (the process that goes on with the command) and
    never returns in the parent, which loads the scan, sends it and exits with the child's status. None where the
    command does not split."""
    found = splits(args)
    if found is None:
        return None
    scan_r, scan_w = os.pipe()
    status_r, status_w = os.pipe()
    sys.stdout.flush()
    sys.stderr.flush()
    parent = os.getpid()
    pid = os.fork()
    if pid == 0:  # the child: the command goes on here
        os.close(scan_w)
        os.close(status_r)
        global _report_fd
        _report_fd = status_w
        _end_with_parent(parent)
        _start_driver(args)
        return ScanAhead(scan_r, found)
    os.close(scan_r)
    os.close(status_w)
    code = 1
    try:
        code = _parent(args, pid, scan_w, status_r)
    finally:
        os._exit(code)


def _end_with_parent(parent: int | None) -> None:
    """A SIGTERM for this child when the command's process ends before it (Linux's parent-death signal): a command
    killed outright (SIGKILL from a job scheduler, `kill -9`) must not leave its GPU work running; the child stops
    as on any SIGTERM, its checkpoint kept. parent None: no such signal any more (the work is done, and the parent
    exits as soon as it has the status)."""
    import ctypes

    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, 0 if parent is None else int(signal.SIGTERM))  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return
    if parent is not None and os.getppid() != parent:  # the parent ended before the signal was asked for
        os.kill(os.getpid(), signal.SIGTERM)


def _start_driver(args) -> None:
    """The CUDA driver (cuInit) and NVML started in a thread while the child imports, unless the command asks for the
    CPU (slwarp.driver). Why: torch's first CUDA call (`torch.cuda.is_available()` as the configuration resolves the
    device) ran cuInit holding the interpreter lock, 0.19 s of a fresh `fast` command on an H100 host (a stack
    sampler). The GPU's context is left to torch here: made in the same thread too, the command took 7.13 s against
    6.91 (one H200 host, 9 and 5 runs; bench/results/command-wall-cuda-h200-fast-context.md), no gain within the
    hosts' noise, where four processes starting at once gain a second (slwarp.driver)."""
    from ..driver import start_driver
    from .neural import _requested_device

    if _requested_device(args) != "cpu":
        start_driver(None)


def _parent(args, child: int, scan_w: int, status_r: int) -> int:
    """Load and send the scan, then wait for the child's status; returns the status to exit with."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the child too, which stops and reports
    signal.signal(signal.SIGTERM, lambda signum, frame: _pass_on(child, signum))
    if hasattr(signal, "SIGHUP"):
        signal.signal(signal.SIGHUP, lambda signum, frame: _pass_on(child, signum))
    try:
        message = ("scan", _load(args))
    except BaseException as e:  # noqa: BLE001 - raised in the child, where the command reports it
        message = ("error", _picklable(e))
    try:
        _send(scan_w, message)
    except OSError:
        pass  # the child ended before reading (e.g. a bad option): its status says why
    finally:
        os.close(scan_w)
        del message  # the scan's memory back while the child runs
    data = _read_exactly(status_r, _STATUS.size)
    if len(data) == _STATUS.size:
        return _STATUS.unpack(data)[0]
    return _status_of(child)  # no status reported: how the child ended


def _load(args):
    """(the scan as the command loads it, its camera's ray grid, its problems: Scan.problems, 0.04 s of the child's
    time for a default-rig scan)."""
    from ..scans.scan import load_scan
    from ..scans.scanner import camera_rays
    from .neural import _pattern_set

    scan = load_scan(args.scans[0], frames=args.frames, outside_paths=args.allow_outside_paths,
                     patterns=_pattern_set(args.patterns))
    return scan, camera_rays(scan.camera), scan.problems()


def _picklable(e: BaseException) -> BaseException:
    """`e` if it survives pickling, else a RuntimeError with its type and message."""
    try:
        pickle.loads(pickle.dumps(e))
        return e
    except Exception:  # noqa: BLE001
        return RuntimeError(f"{type(e).__name__}: {e}")


def _pass_on(child: int, signum: int) -> None:
    try:
        os.kill(child, signum)
    except ProcessLookupError:
        pass


def _status_of(child: int) -> int:
    """The exit status of the ended child (a signal's as the shell gives it: 128 + the signal)."""
    while True:
        try:
            _, status = os.waitpid(child, 0)
            break
        except InterruptedError:
            continue
        except ChildProcessError:
            return 1
    if os.WIFSIGNALED(status):
        return 128 + os.WTERMSIG(status)
    return os.WEXITSTATUS(status) if os.WIFEXITED(status) else 1


def _send(fd: int, message) -> None:
    """`message` pickled (protocol 5: numpy's arrays as out-of-band buffers, written as they are)."""
    buffers: list[pickle.PickleBuffer] = []
    meta = pickle.dumps(message, protocol=5, buffer_callback=buffers.append)
    raws = [b.raw() for b in buffers]
    _write_all(fd, _HEADER.pack(len(meta), len(raws)) + meta)
    for raw in raws:
        _write_all(fd, _SIZE.pack(raw.nbytes))
        _write_all(fd, raw)


def _write_all(fd: int, data) -> None:
    view = memoryview(data).cast("B")
    while view:
        n = os.write(fd, view)
        view = view[n:]


def _read_exactly(fd: int, n: int) -> bytes:
    """Up to n bytes (fewer only at the pipe's end)."""
    out = bytearray(n)
    return bytes(out[: _read_into(fd, memoryview(out))])


def _read_into(fd: int, view: memoryview) -> int:
    """Fill `view` from the pipe (os.readv leaves the interpreter lock free); the bytes read (fewer than the view's
    only at the pipe's end)."""
    got = 0
    while got < len(view):
        n = os.readv(fd, [view[got:]])
        if n == 0:
            break
        got += n
    return got


class ScanAhead:
    """The child's side: a daemon thread reads the parent's message while the command imports; scan() waits for
    it. `found`: the scans the command named (batch.find_scans' Discovery, made before the fork)."""

    def __init__(self, fd: int, found=None):
        self.found = found
        self.problems: list[str] | None = None  # the scan's problems (Scan.problems), once scan() has returned
        self._fd = fd
        self._message, self._error = None, None
        self._thread = threading.Thread(target=self._receive, name="slwarp-scan-receiver", daemon=True)
        self._thread.start()

    def _receive(self) -> None:
        try:
            meta_size, count = _HEADER.unpack(self._read(_HEADER.size))
            meta = self._read(meta_size)
            buffers = [self._read(_SIZE.unpack(self._read(_SIZE.size))[0]) for _ in range(count)]
            self._message = pickle.loads(meta, buffers=buffers)
        except BaseException as e:  # noqa: BLE001 - raised where the command asks for the scan
            self._error = e
        finally:
            os.close(self._fd)

    def _read(self, n: int) -> bytearray:
        out = bytearray(n)
        if _read_into(self._fd, memoryview(out)) < n:
            raise EOFError("the scan's loader ended before it had sent the scan")
        return out

    def scan(self):
        """The loaded Scan, its camera's ray grid placed in camera_rays' cache; the parent's error raised here (a
        ScanError for a bad scan, reported by the command as it would report its own)."""
        self._thread.join()
        if self._error is not None:
            raise RuntimeError(f"the scan could not be received from its loader: {self._error}") from self._error
        kind, value = self._message
        if kind == "error":
            raise value
        scan, rays, self.problems = value
        from ..scans.scanner import cache_rays

        cache_rays(scan.camera, rays)
        return scan


def report_exit(code: int) -> None:
    """In the child of a split command: its standard streams handed back (a pipe reading them sees their end) and
    `code` sent to the parent, which exits with it. Elsewhere nothing."""
    global _report_fd
    if _report_fd is None:
        return
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    try:
        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, 1)
        os.dup2(null, 2)
        os.close(null)
    except OSError:
        pass
    _end_with_parent(None)  # what is left, the runtimes' teardown, ends on its own
    try:
        os.write(_report_fd, _STATUS.pack(int(code)))
        os.close(_report_fd)
    except OSError:
        pass
    _report_fd = None
