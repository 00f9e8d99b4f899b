"""bench.replicates: one simulated scan trained with several seeds, each run's figures and the lost-surface rule's."""
import json

from bench.replicates import main, parse_case, table


def test_cases_parse_and_bad_ones_are_named(capsys):
    assert parse_case("oblique,torus,fast:level_adam_steps=true") == (
        "oblique", "torus", "fast:level_adam_steps=true", {"preset": "fast", "level_adam_steps": True})
    assert main(["--cases", "oblique,torus"]) == 2
    assert "case 'oblique,torus': expected RIG,SCENE,PRESET" in capsys.readouterr().err
    assert main(["--cases", "sideways,torus,fast"]) == 2
    assert "unknown rig geometry 'sideways'" in capsys.readouterr().err


def test_two_seeds_on_the_small_rig(tmp_path, capsys):
    assert main(["--small", "--cases", "default,steps,tiny", "--runs", "2", "--device", "cpu",
                 "--set", "iters=4,init_iters=4,mc_resolution=32", "--out", str(tmp_path), "--stem", "r"]) == 0
    doc = json.loads((tmp_path / "r.json").read_text())
    rows = doc["rows"]
    assert [r["seed"] for r in rows] == [0, 1] and {r["rig"] for r in rows} == {"small"}
    assert all(r["graph_captured"] is False and 0 <= r["surface_shares"]["lost"] <= 1 for r in rows)
    assert "| small steps tiny | 1 |" in (tmp_path / "r.md").read_text()
    assert doc["command"].startswith("python -m bench.replicates --small")


def test_the_table_says_a_lost_surface():
    row = {"rig": "oblique", "scene": "torus", "case": "fast", "seed": 3, "mae": 144.6, "completeness": 0.154,
           "surface_shares": {"lost": 0.62, "searched": 0.31}, "surface_lost": None, "graph_captured": True,
           "wall_s": 3.7}
    assert "| oblique torus fast | 3 | 144.600 | 15.4% | 62.0% | 31.0% | ok | yes | 3.7 |" in table([row])
