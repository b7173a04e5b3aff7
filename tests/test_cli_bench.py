"""The bench commands' one argument set-up and one report writer (no benchmark runs here)."""

import json
from pathlib import Path

import pytest

from cr_nlp.bench.common import read_csv, write_report
from cr_nlp.cli import build_parser, main

BENCHMARKS = ("ik", "plan", "follow", "clearance", "batch")


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
