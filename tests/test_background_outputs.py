"""reconstruct(write_in_background=True): the result returns before its files, the files arrive complete (the same as
a foreground run writes), and a failed write leaves nothing of the run and is raised by wait_written."""
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
