"""Progress output: plain lines every few seconds where the output is not a terminal, a bar where it is."""
import io

from slwarp.neural.training.progress import Progress


class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def test_lines_every_interval_without_redraws():
    out, clock = io.StringIO(), Clock()
    with Progress(100, "training", stream=out, interval_s=5.0, clock=clock) as bar:
        for i in range(100):
            clock.t += 0.25  # 4 it/s: a line every 20 iterations
            bar.set_postfix(loss=f"{1.0 / (i + 1):.4f}")
            bar.update()
    lines = out.getvalue().splitlines()
    assert "\r" not in out.getvalue()
    assert len(lines) == 5  # at 20, 40, 60, 80 and 100 iterations (close does not repeat the last)
    assert lines[0] == "training: 20/100 it (20%), 4 it/s, 20s left | loss 0.0500"
    assert lines[-1] == "training: 100/100 it (100%), 4 it/s, 25s in all | loss 0.0100"


def test_default_interval_when_not_a_terminal_and_nothing_when_disabled():
    out, clock = io.StringIO(), Clock()
    bar = Progress(3, "SDF grid", unit="slab", stream=out, clock=clock)
    assert bar.interval_s == 10.0
    clock.t = 11.0
    bar.update()
    clock.t = 12.0
    bar.update()
    bar.close()  # the final count, not shown yet
    assert out.getvalue().splitlines() == ["SDF grid: 1/3 slab (33%), 0.0909 slab/s, 22s left",
                                           "SDF grid: 2/3 slab (67%), 0.167 slab/s, 6s left"]
    quiet = io.StringIO()
    with Progress(3, "x", stream=quiet, enabled=False, clock=clock) as bar:
        clock.t += 100
        bar.update(3)
    assert quiet.getvalue() == ""


class Terminal(io.StringIO):
    def isatty(self):
        return True


def test_terminal_gets_a_bar():
    out = Terminal()
    with Progress(10, "training", stream=out) as bar:
        bar.update(10)
    assert "\r" in out.getvalue() and "10/10" in out.getvalue()
