"""Device resolution in one place: torch devices from user strings, Warp device names from torch devices."""
import pytest
import torch

from slwarp.devices import DeviceError, torch_device, warp_device, with_index


def test_cpu_and_auto():
    assert torch_device("cpu") == torch.device("cpu")
    assert torch_device("auto") == torch.device("cuda" if torch.cuda.is_available() else "cpu")
    assert torch_device(None) == torch_device("auto")
    assert warp_device(torch.device("cpu")) == "cpu" and warp_device("cpu") == "cpu"
    assert warp_device("auto") == ("cuda:0" if torch.cuda.is_available() else "cpu")


@pytest.mark.parametrize("spec", ["gpu", "cuda:x", "CPU", "cuda0", ""])
def test_malformed_device_names_the_value(spec):
    with pytest.raises(DeviceError, match="'auto', 'cpu', 'cuda' or 'cuda:N'") as e:
        torch_device(spec)
    assert repr(spec) in str(e.value)


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_cuda_without_a_gpu_is_a_clear_error():
    with pytest.raises(DeviceError, match="no CUDA device is available"):
        torch_device("cuda:0")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_device_names():
    assert torch_device("cuda") == torch.device("cuda")
    assert warp_device(torch.device("cuda")) == f"cuda:{torch.cuda.current_device()}"
    assert warp_device(torch.device("cuda", 0)) == "cuda:0"
    with pytest.raises(DeviceError, match="CUDA device"):
        torch_device(f"cuda:{torch.cuda.device_count()}")


@pytest.mark.parametrize("spec, hint", [("gpu", "cuda or cuda:N"), ("mps", "Apple GPUs are not supported")])
def test_devices_users_try_are_refused_with_the_allowed_forms(spec, hint):
    from slwarp.devices import DeviceError, torch_device, warp_device

    for resolve in (torch_device, warp_device):
        with pytest.raises(DeviceError) as e:
            resolve(spec)
        assert repr(spec) in str(e.value) and "'auto', 'cpu', 'cuda' or 'cuda:N'" in str(e.value) and hint in str(e.value)


def test_with_index_names_the_current_cuda_device():
    assert with_index(torch.device("cpu")) == torch.device("cpu")
    assert with_index(torch.device("cuda", 0)) == torch.device("cuda", 0)  # no lookup: no CUDA needed
    if torch.cuda.is_available():
        assert with_index(torch.device("cuda")) == torch.device("cuda", torch.cuda.current_device())


def test_the_early_driver_start_leaves_torch_a_working_cuda_or_none():
    """start_driver in a fresh process, then torch's own start: on a GPU machine torch computes on the context the
    thread made; without a driver the thread ends quietly and torch says CUDA is absent."""
    import subprocess
    import sys

    code = ("import torch; from slwarp.driver import start_driver, _RETAINED; t = start_driver(0); "
            "t is None or t.join(30); ok = torch.cuda.is_available(); "
            "print(ok, len(_RETAINED), float((torch.ones(4, device='cuda') * 2).sum()) if ok else None)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    ok, retained, total = out.stdout.split()
    if ok == "True":
        assert retained == "1" and float(total) == 8.0
    else:
        assert total == "None"
