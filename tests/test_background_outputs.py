"""reconstruct(write_in_background=True): the result returns before its files, the files arrive complete (the same as
a foreground run writes), and a failed write leaves nothing of the run and is raised by wait_written."""
from pathlib import Path

import numpy as np
import pytest

from slwarp.neural.config import preset
from slwarp.neural.reconstruct import reconstruct
from slwarp.sim.simulate import SimOptions, simulate_scene

FILES = ("depth.npy", "depth.png", "confidence.npy", "pixel_fate.png", "mesh.ply", "points.ply", "metrics.json",
         "timings.json", "config.yaml", "history.json", "train/checkpoint.pt")


@pytest.fixture(scope="module")
def scan():
    return simulate_scene("spheres", "random6", rig="small", options=SimOptions(seed=2))


def cfg():
    return preset("tiny", device="cpu", iters=4, init_iters=2, mc_resolution=32, rays=64)


def test_files_written_in_the_background_are_complete(scan, tmp_path):
    res = reconstruct(scan, cfg(), out_dir=tmp_path / "bg", progress=False, write_in_background=True)
    res.wait_written()
    assert res.writer is None
    for f in FILES:
        assert (tmp_path / "bg" / f).is_file(), f
    np.testing.assert_array_equal(np.load(tmp_path / "bg" / "depth.npy"), res.depth.astype(np.float32))
    assert not list(tmp_path.glob(".bg.partial-*"))  # the staging folder was moved into place
    fg = reconstruct(scan, cfg(), out_dir=tmp_path / "fg", progress=False)
    assert fg.writer is None
    assert sorted(p.name for p in (tmp_path / "fg").iterdir()) == sorted(p.name for p in (tmp_path / "bg").iterdir())


def test_a_failed_background_write_leaves_nothing_and_is_raised(scan, tmp_path, monkeypatch):
    import slwarp.neural.reconstruct as module

    def broken(folder, depth):
        raise OSError(28, "No space left on device", str(folder / "depth.npy"))

    monkeypatch.setattr(module, "write_depth", broken)
    res = reconstruct(scan, cfg(), out_dir=tmp_path / "run", progress=False, write_in_background=True)
    with pytest.raises(OSError, match="No space left"):
        res.wait_written()
    leftovers = [p for p in tmp_path.iterdir() if p.name != "run"] + [
        p for p in (tmp_path / "run").rglob("*") if p.is_file() and p.name != "checkpoint.pt"]
    assert leftovers == []


def test_overlapped_batch_gives_the_same_results_in_order(scan, tmp_path, monkeypatch):
    """run_scans with overlap (each scan's extraction and files in a thread while the next trains; on by default on
    a GPU, forced here on the CPU): the same depth maps and rows as one scan after another, rows reported in order,
    each complete when reported, a broken scan failed alone; the extraction of a scan waits for the one before."""
    import threading

    import slwarp.neural.reconstruct as module
    from slwarp.batch import BatchOptions, ScanJob, run_scans

    for name in ("a", "b"):
        scan.save(tmp_path / "scans" / name)
    scan.save(tmp_path / "scans" / "broken")
    (tmp_path / "scans" / "broken" / "images" / f"002_{scan.names[2]}.png").unlink()
    names = ("a", "broken", "b")
    finishing, lock = [], threading.Lock()  # the extraction threads alive at once, at most one
    finish = module._finish

    def counted(trained):
        with lock:
            finishing.append(threading.current_thread().name)
            assert len(finishing) == 1, finishing
        try:
            return finish(trained)
        finally:
            with lock:
                finishing.pop()

    monkeypatch.setattr(module, "_finish", counted)
    rows = {}
    for overlap in (False, True):
        jobs = [ScanJob(n, str(tmp_path / "scans" / n), str(tmp_path / f"out-{overlap}" / n)) for n in names]
        reported = []
        def report(r):
            reported.append((r.name, r.status, (Path(r.out_dir) / "config.yaml").is_file()))

        got = run_scans(jobs, cfg(), BatchOptions(log=False, overlap=overlap), on_row=report)
        assert reported == [("a", "done", True), ("broken", "failed", False), ("b", "done", True)], overlap
        rows[overlap] = got
    for n, plain, overlapped in zip(names, rows[False], rows[True]):
        assert (plain.name, plain.status, plain.valid_share, plain.mae) == (
            overlapped.name, overlapped.status, overlapped.valid_share, overlapped.mae), n
        if plain.status == "done":
            assert overlapped.seconds > 0 and overlapped.iterations == plain.iterations
            np.testing.assert_array_equal(np.load(tmp_path / "out-False" / n / "depth.npy"),
                                          np.load(tmp_path / "out-True" / n / "depth.npy"))
    assert rows[True][1].error.startswith("ScanError:")


def test_overlap_flag_of_reconstruct_and_watch():
    """--overlap / --no-overlap reach the batch's options (absent: None, on a GPU only)."""
    from slwarp.cli import build_parser
    from slwarp.cli.neural import _batch_options

    for flags, want in (([], None), (["--no-overlap"], False), (["--overlap"], True)):
        argv = ["reconstruct", "a", "b", "--out", "o", *flags]
        assert _batch_options(build_parser(argv).parse_args(argv), progress=False).overlap is want
        argv = ["watch", "inbox", "--out", "o", *flags]
        assert build_parser(argv).parse_args(argv).overlap is want
