"""bench.fates: the errors and missing pixels of a kept neural run, by pixel fate."""
import numpy as np

from bench.fates import fate_table, main


def test_fate_table_counts_gross_errors_and_pixels_gc7_has(tmp_path, capsys):
    fates = np.array(["measured", "low_confidence", "no_contrast"])
    err = np.array([[0.5, 120.0, np.nan], [-8.0, np.nan, np.nan]], np.float16)
    fate = np.array([[0, 0, 1], [0, 1, 2]], np.uint8)
    np.savez(tmp_path / "cpu-hashgrid__small__rods__s0__cpu-hashgrid.npz", error=err, fate=fate, fates=fates)
    gc7 = np.array([[0.1, 0.2, 0.3], [0.1, 0.2, np.nan]], np.float16)  # GC(7) has both dropped pixels but one
    np.savez(tmp_path / "classical__small__rods__s0__GC7interp.npz", error=gc7)
    rows = {r["fate"]: r for r in fate_table(tmp_path / "cpu-hashgrid__small__rods__s0__cpu-hashgrid.npz")}
    m = rows["measured"]
    assert (m["pixels"], m["with_depth"], m["gross"], m["gross_sum_mm"]) == (3, 3, 2, 128.0)
    assert m["gross_mean_mm"] == 56.0 and m["gc7_has_we_lack"] == 0
    assert (rows["low_confidence"]["pixels"], rows["low_confidence"]["gc7_has_we_lack"]) == (2, 2)
    assert rows["no_contrast"]["gc7_has_we_lack"] == 0
    assert main([str(tmp_path), "--match", "rods", "--json", str(tmp_path / "f.json")]) == 0
    assert "| measured | 3 | 3 | 2 | 128 | +56.0 | 0 |" in capsys.readouterr().out
    import json

    doc = json.loads((tmp_path / "f.json").read_text())
    assert doc["runs"]["cpu-hashgrid__small__rods__s0__cpu-hashgrid"][0]["gross"] == 2
    assert main([str(tmp_path), "--match", "bunny"]) == 2
