"""The README's drop-in example runs as printed (a user's first contact with the renderer API)."""
from __future__ import annotations

import math
import re
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_drop_in_example_runs(capsys):
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    example = next(b for b in blocks if "StructuredLightRenderer" in b)
    scope: dict = {}
    exec(compile(example, "README.md", "exec"), scope)
    losses = scope["losses"]
    assert all(math.isfinite(float(v.detach())) for v in (losses.color, losses.surface, losses.eikonal))
    assert "L_rc" in capsys.readouterr().out


def test_readme_hashgrid_example_runs(capsys):
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    example = next(b for b in blocks if "HashGridSDF(" in b)
    scope: dict = {}
    exec(compile(example, "README.md", "exec"), scope)
    losses, sdf = scope["losses"], scope["sdf"]
    assert math.isfinite(float(losses.color.detach())) and math.isfinite(float(losses.eikonal.detach()))
    assert sdf.n_active == 6 and float(sdf.table.detach().abs().max()) > 1e-3  # the tables moved off their 1e-4 init
    assert "hash grid: L_rc" in capsys.readouterr().out


def test_readme_config_example_is_a_valid_config(tmp_path):
    from slwarp.neural.config import load_config, preset

    block = next(b for b in re.findall(r"```yaml\n(.*?)```", README.read_text(), flags=re.S) if "schedule:" in b)
    (tmp_path / "c.yaml").write_text(block)
    cfg = load_config(tmp_path / "c.yaml", base=preset("cpu"))
    assert cfg.schedule.iters == 2000 and cfg.schedule.lr == 5e-4 and cfg.extraction.mc_resolution == 256


def test_readme_is_short_and_its_results_links_exist():
    """README stays a user's page (at most 300 lines) and every figure's link points at a results file that exists."""
    text = README.read_text()
    assert len(text.splitlines()) <= 300
    links = re.findall(r"\]\((bench/results/[^)#]+)\)", text)
    assert links and all((README.parent / link).is_file() for link in links), [l for l in links if not (README.parent / l).is_file()]
