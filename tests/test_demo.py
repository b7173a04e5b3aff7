"""``cr-nlp demo`` (the README's main job) writes its summary, results and figures."""

import json

from cr_nlp.cli import main


def test_demo_ik_task_writes_results_and_figure(tmp_path, capsys) -> None:
    out = tmp_path / "demo"
    assert main(["demo", "--tasks", "ik", "--penalty-only", "--out", str(out)]) == 0
    table = capsys.readouterr().out
    assert "| IK | 20 targets, lattice | 20/20 |" in table, table
    result = json.loads((out / "ik_result.json").read_text())
    assert len(result["results"]) == 20
    assert all(r["success"] and r["collision_free"] for r in result["results"])
    assert (out / "ik.png").stat().st_size > 10_000
    assert (out / "summary.md").read_text().startswith("| task |")
