"""The bench commands' one argument set-up and one report writer (no benchmark runs here)."""

import json
from pathlib import Path

import pytest

from cr_nlp.bench._common import (
    provenance_line,
    read_csv,
    replace_section,
    section_markers,
    write_report,
)
from cr_nlp.cli import build_parser, main

BENCHMARKS = ("ik", "plan", "follow", "clearance", "batch", "profile")


@pytest.mark.parametrize("name", BENCHMARKS)
def test_every_benchmark_shares_the_common_options(name: str) -> None:
    args = build_parser().parse_args(["bench", name, "--devices", "1", "--no-progress"])
    assert args.out == f"bench_results/{name}" and args.devices == 1 and args.no_progress
    assert callable(args.run)
    other = build_parser().parse_args(["bench", name, "--out", "x"])
    assert other.out == "x" and other.devices is None and not other.no_progress
    if name != "ik":  # ik runs its fixed robot lists
        assert other.robot == "tdcr3"


def test_bad_repeats_is_a_usage_error(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert main(["bench", "follow", "--repeats", "0", "--out", str(tmp_path / "out")]) == 2
    assert "--repeats must be at least 1" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_a_crowded_clutter_scene_is_a_usage_error(
        tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch) -> None:
    from cr_nlp.bench import tension_clutter

    def crowded(**_: object) -> None:
        raise tension_clutter.CrowdedScene("clutter benchmark: 0 of 32 random tension sets")

    monkeypatch.setattr(tension_clutter, "run_tension_clutter_benchmark", crowded)
    assert main(["bench", "tension", "--suite", "clutter", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == ("cr-nlp bench: error: clutter benchmark: 0 of 32 random tension sets "
                   "(try another --seed)")


def test_the_loop_suite_names_a_robot_it_cannot_drive(
        tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert main(["bench", "tension", "--robot", "ftdcr_v6_cosserat", "--out",
                 str(tmp_path)]) == 2
    assert ("--robot ftdcr_v6_cosserat has 9 tendons, 3 per segment"
            in capsys.readouterr().err)


def test_the_report_writer_prints_and_writes_every_file(
        tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    rows = [{"robot": "tdcr3", "ms": 1.5, "note": None}, {"robot": "tdcr4_ext", "ms": 2.0}]
    sweep = [{"iterations": 10, "success_pct": 90.0}]
    env = {"python": "3.11", "cores": "2"}
    path = write_report("demo_bench", "# report\n\n| a |", tmp_path / "out",
                        {"demo_bench": rows, "sweep": sweep}, env, {"sizes": {"targets": 5}},
                        {"demo_bench": ("robot", "ms")})
    assert capsys.readouterr().out.strip() == "# report\n\n| a |"
    assert path == tmp_path / "out" / "demo_bench.md" and path.read_text() == "# report\n\n| a |\n"
    assert read_csv(tmp_path / "out" / "demo_bench.csv") == [
        {"robot": "tdcr3", "ms": "1.5"}, {"robot": "tdcr4_ext", "ms": "2.0"}]
    assert read_csv(tmp_path / "out" / "sweep.csv") == [{"iterations": "10",
                                                        "success_pct": "90.0"}]
    record = json.loads((tmp_path / "out" / "environment.json").read_text())
    assert record == {"environment": env, "sizes": {"targets": 5}}
    assert write_report("x", "quiet", None, echo=False) is None
    assert capsys.readouterr().out == ""


ENV = {"date": "2026-11-24 21:00 UTC", "python": "3.11.7", "jax": "0.10.2", "casadi": "3.8.2",
       "numpy": "2.4.6", "backend": "cpu", "devices": "cpu:0, cpu:1", "cpu": "Test CPU",
       "cores": "2", "load average (1, 5, 15 min)": "0.10, 0.20, 0.30"}


def test_a_report_becomes_its_own_section_of_the_benchmarks_file() -> None:
    report = "# IK benchmark\n\n| a |\n|---:|\n| 1 |\n\n## Environment\n\n- cores: 2\n"
    text = replace_section("# Benchmarks\n\nBy hand.\n", "ik-free", report,
                           "cr-nlp bench ik --suite free", ENV)
    begin, end = section_markers("ik-free")
    assert text.startswith("# Benchmarks\n\nBy hand.\n\n" + begin + "\n### IK benchmark\n\n")
    assert text.endswith("#### Environment\n\n- cores: 2\n\n" + end + "\n")
    line = provenance_line("cr-nlp bench ik --suite free", ENV)
    assert line in text
    for fact in ("`cr-nlp bench ik --suite free`", "2026-11-24 21:00 UTC", "Python 3.11.7",
                 "jax 0.10.2", "casadi 3.8.2", "numpy 2.4.6", "Test CPU", "2 cores",
                 "cpu:0, cpu:1"):
        assert fact in line
    # A second suite is appended; running the first again replaces only its own section.
    text = replace_section(text, "follow", "# Follow\n\n| b |\n", "cr-nlp bench follow", ENV)
    again = replace_section(text + "\nAfter.\n", "ik-free", "# IK benchmark\n\n| a |\n| 2 |\n",
                            "cr-nlp bench ik --suite free --repeats 5", ENV)
    assert again.count(begin) == 1 and again.count(end) == 1
    assert "| 2 |" in again and "| 1 |" not in again and "--repeats 5" in again
    assert "By hand." in again and "\nAfter.\n" in again and "| b |" in again
    assert again.index(begin) < again.index(section_markers("follow")[0])
    with pytest.raises(ValueError, match="ik-free"):
        replace_section(begin + "\nno end\n", "ik-free", report, "cr-nlp bench ik", ENV)


def test_bench_markdown_writes_the_section_with_command_and_environment(
        tmp_path: Path) -> None:
    doc = tmp_path / "benchmarks.md"
    doc.write_text("# Benchmarks\n\nKept.\n")
    argv = ["bench", "clearance", "--configs", "64", "--repeats", "1", "--scene", "lattice",
            "--out", str(tmp_path / "out"), "--markdown", str(doc)]
    for _ in range(2):  # the second run replaces the section written by the first
        assert main(argv) == 0
    text = doc.read_text()
    begin, end = section_markers("clearance")
    assert text.startswith("# Benchmarks\n\nKept.\n") and text.count(begin) == 1
    section = text[text.index(begin):text.index(end)]
    report = (tmp_path / "out" / "clearance.md").read_text()
    table = [line for line in report.splitlines() if line.startswith("|")]
    assert table and all(line in section for line in table)
    env = json.loads((tmp_path / "out" / "environment.json").read_text())["environment"]
    assert provenance_line("cr-nlp " + " ".join(argv), env) in section
