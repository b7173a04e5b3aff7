"""``cr-nlp bench batch`` on tiny sizes: its rows, ratios and documented files."""

import json

import pytest

from cr_nlp.bench._common import read_csv
from cr_nlp.bench.batch import run_batch_benchmark


def test_the_batch_benchmark_writes_its_rows_and_ratios(tmp_path):
    rows = run_batch_benchmark(
        targets=12, workers=(1,), modes=("penalty",), chunk=6, out=tmp_path / "out", progress=False
    )
    by_runner = {row["runner"]: row for row in rows}
    assert set(by_runner) == {"in-process", "cr-nlp ik --out", "batch, 1 workers",
                              "1 processes, no Dask"}
    local, batch = by_runner["in-process"], by_runner["batch, 1 workers"]
    # cr-nlp ik's own work: the same solve, then its RESULT.json (in the scratch folder).
    cli = by_runner["cr-nlp ik --out"]
    assert cli["same_success"] is True and cli["speedup"] is None and cli["targets"] == 12
    assert batch["vs_cli"] == pytest.approx(batch["total_s"] / cli["total_s"])
    assert cli["vs_in_process"] == pytest.approx(cli["total_s"] / local["total_s"])
    plain = by_runner["1 processes, no Dask"]
    # The machine's ceiling row: the same targets solved in a plain spawned process.
    assert plain["targets"] == 12 and plain["success_pct"] == 100.0
    assert plain["same_success"] is True and plain["speedup"] == 1.0 and plain["chunk"] is None
    assert local["targets"] == batch["targets"] == 12
    assert local["success_pct"] == batch["success_pct"] == 100.0
    assert batch["chunk"] == 6 and batch["speedup"] == 1.0 and local["speedup"] is None
    assert batch["same_success"] is True and batch["max_pose_error"] < 1e-2
    assert batch["vs_in_process"] == pytest.approx(batch["total_s"] / local["total_s"])
    assert batch["per_second"] == pytest.approx(12 / batch["total_s"])
    csv_rows = read_csv(tmp_path / "out" / "batch.csv")
    assert [r["runner"] for r in csv_rows] == [row["runner"] for row in rows]
    assert "| penalty | batch, 1 workers |" in (tmp_path / "out" / "batch.md").read_text()
    env = json.loads((tmp_path / "out" / "environment.json").read_text())["environment"]
    assert "load average (1, 5, 15 min)" in env and "chunk=6" in env["settings"]
