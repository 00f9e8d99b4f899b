"""bench/search_only.py: the depth search alone beside Gray code, on the CPU's small rig (a smoke test; the figures
are only checked for sense), and its refusal of a malformed --designs entry."""
import json

import pytest

from bench import search_only


def test_search_only_smoke_on_cpu(tmp_path):
    search_only.main(["--smoke", "--out", str(tmp_path)])
    doc = json.loads((tmp_path / "search-only-small.json").read_text())
    rows = doc["scenes"]["spheres"]
    assert set(rows) == {"random 6, search", "GC(7) interp"}
    for m in rows.values():
        assert 0.5 < m["completeness"] <= 1.0 and 0.0 <= m["mae"] < 5.0 and 0.0 <= m["over_5mm"] < 0.1
    md = (tmp_path / "search-only-small.md").read_text()
    assert "## spheres" in md and "| GC(7) interp |" in md


def test_search_only_refuses_a_bad_design_entry(tmp_path):
    with pytest.raises(SystemExit, match="STEP:PATH"):
        search_only.main(["--smoke", "--designs", "x:somewhere.yaml", "--out", str(tmp_path)])
