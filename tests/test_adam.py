"""training.adam.Adam against torch.optim.Adam: the same updates (bit for bit on the CPU, to float rounding of the
fused kernel on CUDA), the same state layout both ways, and no torch._dynamo import on the way."""
import copy
import subprocess
import sys

import pytest
import torch

from slwarp.neural.training.adam import Adam

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


def _problem(device, seed=0):
    g = torch.Generator().manual_seed(seed)
    a = torch.nn.Parameter(torch.randn(64, 8, generator=g).to(device))
    b = torch.nn.Parameter(torch.randn(5, generator=g).to(device))
    c = torch.nn.Parameter(torch.randn(1, generator=g).to(device))
    target = torch.randn(64, 8, generator=g).to(device)
    return [a, b, c], target


def _loss(params, target, it):
    a, b, c = params
    return ((a * (1 + 0.1 * it) - target) ** 2).mean() + (b ** 3).sum() * 0.01 + (c.exp() - 2) ** 2


def _groups(params, lrs=(1e-2, 3e-3)):
    a, b, c = params
    return [{"params": [a], "lr": lrs[0], "base_lr": lrs[0]}, {"params": [b, c], "lr": lrs[1], "base_lr": lrs[1]}]


def _run(opt, params, target, iters, start=0):
    for it in range(start, start + iters):
        opt.zero_grad(set_to_none=True)
        _loss(params, target, it).sum().backward()
        opt.step()


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("capturable", [False, True])
def test_updates_match_torch_optim_adam(device, capturable):
    if capturable and device == "cpu":
        pytest.skip("capturable learning rates are a CUDA-graph matter")
    ours_p, target = _problem(device)
    ref_p, _ = _problem(device)
    ours = Adam(_groups(ours_p), lr=1e-3)
    ours.configure(torch.device(device), capturable=capturable)
    ref = torch.optim.Adam(_groups(ref_p), lr=1e-3, fused=device == "cuda", capturable=capturable and device == "cuda")
    _run(ours, ours_p, target, 25)
    _run(ref, ref_p, target, 25)
    for p, q in zip(ours_p, ref_p):
        if device == "cpu":
            assert torch.equal(p, q)
        else:
            torch.testing.assert_close(p, q, rtol=1e-6, atol=1e-7)
    st = ours.state[ours_p[0]]
    assert float(st["step"]) == 25.0 and st["step"].device.type == device


def test_group_without_gradients_keeps_no_state():
    params, target = _problem("cpu")
    frozen = torch.nn.Parameter(torch.ones(3))
    opt = Adam([{"params": params, "lr": 1e-2}, {"params": [frozen], "lr": 1e-2}], lr=1e-3)
    _run(opt, params, target, 2)
    assert frozen not in opt.state and torch.equal(frozen, torch.ones(3))


def test_state_dict_round_trips_with_torch_optim_adam():
    """Ours -> torch and torch -> ours: training continues as if uninterrupted (old checkpoints hold torch's)."""
    params, target = _problem("cpu")
    ref_params, _ = _problem("cpu")
    ref = torch.optim.Adam(_groups(ref_params), lr=1e-3)
    _run(ref, ref_params, target, 10)

    # torch's state into ours
    mine_params = [torch.nn.Parameter(p.detach().clone()) for p in ref_params]
    mine = Adam(_groups(mine_params), lr=1e-3)
    mine.load_state_dict(copy.deepcopy(ref.state_dict()))   # as through a checkpoint file
    assert mine.param_groups[0]["base_lr"] == 1e-2
    _run(mine, mine_params, target, 10, start=10)
    _run(ref, ref_params, target, 10, start=10)
    for p, q in zip(mine_params, ref_params):
        assert torch.equal(p, q)

    # ours into torch's
    back_params = [torch.nn.Parameter(p.detach().clone()) for p in mine_params]
    back = torch.optim.Adam(_groups(back_params), lr=1e-3)
    back.load_state_dict(copy.deepcopy(mine.state_dict()))
    _run(back, back_params, target, 5, start=20)
    _run(mine, mine_params, target, 5, start=20)
    for p, q in zip(mine_params, back_params):
        assert torch.equal(p, q)
    del params


def test_load_state_dict_rejects_a_different_model():
    params, target = _problem("cpu")
    opt = Adam(_groups(params), lr=1e-3)
    _run(opt, params, target, 1)
    other = [torch.nn.Parameter(torch.zeros(3, 3)), torch.nn.Parameter(torch.zeros(5)), torch.nn.Parameter(torch.zeros(1))]
    with pytest.raises(ValueError, match="shape"):
        Adam(_groups(other), lr=1e-3).load_state_dict(opt.state_dict())
    with pytest.raises(ValueError, match="groups"):
        Adam([{"params": other, "lr": 1e-3}], lr=1e-3).load_state_dict(opt.state_dict())


def test_a_step_imports_no_dynamo():
    """The reason this class exists: torch.optim.Adam's first call imports torch._dynamo (seconds in a fresh
    process)."""
    code = ("import sys, torch\n"
            "from slwarp.neural.training.adam import Adam\n"
            "p = torch.nn.Parameter(torch.ones(4)); opt = Adam([{'params': [p], 'lr': 0.1}], lr=0.1)\n"
            "(p ** 2).sum().backward(); opt.step(); opt.zero_grad(); opt.state_dict()\n"
            "print('torch._dynamo' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"


# --- segments: a hash grid's levels, each counting its own steps ---------------------------------------

def _segment_problem(device, seed=1):
    """A [12, 2] parameter of three segments (rows 0-3, 4-8, 9-11) whose gradient is zero outside the segments
    switched on, as a hash grid's tables give it."""
    g = torch.Generator().manual_seed(seed)
    p = torch.nn.Parameter(torch.randn(12, 2, generator=g).to(device))
    target = torch.randn(12, 2, generator=g).to(device)
    return p, target


SEGMENTS = [(0, 4), (4, 9), (9, 12)]


def _segment_step(opt, p, target, active, it):
    mask = torch.zeros(12, 1, device=p.device)
    mask[:SEGMENTS[int(active) - 1][1]] = 1.0
    opt.zero_grad(set_to_none=True)
    ((p * (1 + 0.05 * it) - target) ** 2 * mask).sum().backward()
    opt.step()


@pytest.mark.parametrize("device", DEVICES)
def test_a_segment_switched_on_late_steps_as_a_new_parameter(device):
    """Segment 2 switched on at step 11 moves exactly as a fresh Adam on its rows would from there (its own bias
    correction), while segment 3, never on, does not move; with every segment on from the start the segmented
    optimiser is plain Adam."""
    p, target = _segment_problem(device)
    start = p.detach().clone()
    active = torch.tensor([1], dtype=torch.int32, device=device)
    opt = Adam([{"params": [p], "lr": 1e-2, "segments": SEGMENTS, "active_segments": active}], lr=1e-2)
    opt.configure(torch.device(device), capturable=False)
    for it in range(10):
        _segment_step(opt, p, target, active, it)
    assert torch.equal(p[4:], start[4:])
    # a fresh Adam on segment 2's rows, from the values they have when it is switched on
    q = torch.nn.Parameter(p.detach()[4:9].clone())
    fresh = Adam([{"params": [q], "lr": 1e-2}], lr=1e-2)
    fresh.configure(torch.device(device), capturable=False)
    active.fill_(2)
    for it in range(10, 15):
        _segment_step(opt, p, target, active, it)
        fresh.zero_grad(set_to_none=True)
        ((q * (1 + 0.05 * it) - target[4:9]) ** 2).sum().backward()
        fresh.step()
    torch.testing.assert_close(p.detach()[4:9], q.detach(), rtol=1e-6, atol=1e-7)
    assert torch.equal(p[9:], start[9:])
    assert opt.state[p]["segment_steps"].tolist() == [15.0, 5.0, 0.0]

    # all segments on from the start: the same run as one count for the whole parameter
    p1, _ = _segment_problem(device)
    p2, _ = _segment_problem(device)
    full = torch.tensor([3], dtype=torch.int32, device=device)
    seg = Adam([{"params": [p1], "lr": 1e-2, "segments": SEGMENTS, "active_segments": full}], lr=1e-2)
    plain = Adam([{"params": [p2], "lr": 1e-2}], lr=1e-2)
    for o in (seg, plain):
        o.configure(torch.device(device), capturable=False)
    for it in range(8):
        _segment_step(seg, p1, target, full, it)
        _segment_step(plain, p2, target, full, it)
    torch.testing.assert_close(p1, p2, rtol=1e-6, atol=1e-7)


def test_one_count_gives_a_late_segment_larger_first_steps():
    """Why segments: with one count, the segment switched on at step 201 takes its first steps at about 1.5-3x
    the rate (the second moment's correction of step 200); with its own count, at about the rate."""
    moves = {}
    for segmented in (False, True):
        p, target = _segment_problem("cpu")
        active = torch.tensor([1], dtype=torch.int32)
        group = {"params": [p], "lr": 1e-3}
        if segmented:
            group.update(segments=SEGMENTS, active_segments=active)
        opt = Adam([group], lr=1e-3)
        for it in range(200):
            _segment_step(opt, p, target, active, 0)
        active.fill_(2)
        before = p.detach()[4:9].clone()
        for it in range(5):
            _segment_step(opt, p, target, active, 0)
        moves[segmented] = float((p.detach()[4:9] - before).abs().mean()) / 5 / 1e-3
    assert 0.9 < moves[True] < 1.05
    assert moves[False] > 1.5 * moves[True]


def test_segment_steps_round_trip_through_the_state_dict():
    p, target = _segment_problem("cpu")
    active = torch.tensor([2], dtype=torch.int32)
    opt = Adam([{"params": [p], "lr": 1e-2, "segments": SEGMENTS, "active_segments": active}], lr=1e-2)
    for it in range(3):
        _segment_step(opt, p, target, active, it)
    state = copy.deepcopy(opt.state_dict())
    assert "active_segments" not in state["param_groups"][0]
    q = torch.nn.Parameter(p.detach().clone())
    other = Adam([{"params": [q], "lr": 1e-2, "segments": SEGMENTS, "active_segments": active}], lr=1e-2)
    other.load_state_dict(state)
    assert other.state[q]["segment_steps"].tolist() == [3.0, 3.0, 0.0]
    _segment_step(opt, p, target, active, 3)
    _segment_step(other, q, target, active, 3)
    assert torch.equal(p, q)


def test_segments_must_lie_in_the_parameter():
    p, _ = _segment_problem("cpu")
    active = torch.tensor([1], dtype=torch.int32)
    with pytest.raises(ValueError, match="do not lie"):
        Adam([{"params": [p], "lr": 1e-2, "segments": [(0, 4), (4, 13)], "active_segments": active}], lr=1e-2)
    with pytest.raises(ValueError, match="one parameter"):
        Adam([{"params": [p], "lr": 1e-2, "segments": SEGMENTS}], lr=1e-2)
