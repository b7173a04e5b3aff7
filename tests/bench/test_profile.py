"""``cr-nlp bench profile``: a traced warm IK solve summed per timeline."""

from pathlib import Path

import numpy as np
import pytest

from cr_nlp.bench._common import read_csv
from cr_nlp.bench.profile import busy_ms, run_profile_benchmark
from cr_nlp.cli import main


def test_busy_time_counts_overlapping_and_nested_events_once() -> None:
    # [0, 10) ∪ [5, 15) ∪ [20, 30) ∪ [21, 22) (nested): 15 + 10 = 25 ns
    starts = np.array([20.0, 0.0, 21.0, 5.0])
    ends = np.array([30.0, 10.0, 22.0, 15.0])
    assert busy_ms(starts, ends) == pytest.approx(25e-6)
    assert busy_ms(np.zeros(0), np.zeros(0)) == 0.0


def test_a_traced_solve_is_summed_per_timeline(tmp_path: Path) -> None:
    found = run_profile_benchmark("tdcr3", targets=20, top=3, out=tmp_path)
    assert found["success"] == 1.0 and found["traced_s"] > 0.0
    names = [row["timeline"] for row in found["timelines"]]
    # the compiled programs' timelines: XLA's CPU threads, or a device's streams
    assert any("tf_XLAEigen" in n or n.startswith("/device:") for n in names), names
    for row in found["timelines"]:
        assert 0.0 < row["busy_ms"] <= row["span_ms"] + 1e-9
    # the host's Python timeline is the solve only, not the trace's own stop (seconds)
    python = [row for row in found["timelines"] if "XLA" not in row["timeline"]
              and not row["timeline"].startswith("/device:")]
    assert python and all(row["busy_ms"] <= 1.01e3 * found["traced_s"] for row in python)
    ops = read_csv(tmp_path / "ops.csv")
    assert ops and all(int(r["count"]) >= 1 and float(r["total_ms"]) > 0.0 for r in ops)
    assert len([r for r in ops if r["timeline"] == names[0]]) <= 3   # --top
    assert (tmp_path / "profile.md").read_text().startswith("## Where a warm IK solve")
    assert list((tmp_path / "trace").rglob("*.xplane.pb"))


def test_bad_sizes_are_a_usage_error(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert main(["bench", "profile", "--targets", "0", "--out", str(tmp_path / "o")]) == 2
    assert "--targets and --top must be at least 1" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()
