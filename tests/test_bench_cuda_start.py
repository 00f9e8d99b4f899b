"""bench.cuda_start on a machine without a GPU: it says so and measures nothing; its child script runs as written."""
import torch

from bench import cuda_start


def test_without_a_gpu_it_says_so(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(cuda_start, "gpu_ids", lambda: [])
    assert cuda_start.main(["--out", str(tmp_path)]) == 1
    assert "no GPU visible" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


def test_the_child_script_compiles_and_starts_the_driver_first():
    compile(cuda_start._CHILD, "child", "exec")
    child = cuda_start._CHILD
    assert 0 <= child.index("start_driver(0)") < child.index("import torch")  # the driver first, the import beside it
    if torch.cuda.is_available():
        rows = cuda_start.one_round(1, True, cuda_start.gpu_ids())
        assert rows[0]["total_s"] >= rows[0]["torch_s"] > 0
