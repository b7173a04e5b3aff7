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


def test_follow_programs_compile_beside_the_earlier_tasks(tmp_path, monkeypatch) -> None:
    """The follow task's programs start compiling before the first task and are awaited
    just before following; a demo that starts with following starts nothing ahead."""
    from cr_nlp import demo

    events: list[str] = []

    class Ahead:
        def join(self) -> None:
            events.append("join")

    def ahead() -> Ahead:
        events.append("ahead")
        return Ahead()

    def task(name: str):
        def run(out, exact) -> demo.DemoRow:
            events.append(name)
            return demo.DemoRow(name, "", "", "", 0.0, 0.0, [])
        return run

    monkeypatch.setattr(demo, "_compile_follow_ahead", ahead)
    monkeypatch.setattr(demo, "TASKS", {n: task(n) for n in ("ik", "plan", "follow")})
    demo.run_demo(tmp_path, tasks=("ik", "plan", "follow"), progress=False)
    assert events == ["ahead", "ik", "plan", "join", "follow"]
    events.clear()
    demo.run_demo(tmp_path, tasks=("follow", "ik"), progress=False)
    assert events == ["follow", "ik"]
