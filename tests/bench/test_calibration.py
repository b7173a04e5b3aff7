"""``cr-nlp bench calibration`` (the train-only fold score): the families of the bundled
recording and the refusals; the fits themselves are benchmark runs, not tests."""

from __future__ import annotations

import numpy as np
import pytest

from cr_nlp.bench.calibration import FAMILIES, family_labels, family_of, run_calibration_benchmark


def test_every_training_row_belongs_to_one_family() -> None:
    labels = family_labels("ftdcr_v6")
    names, counts = np.unique(labels, return_counts=True)
    assert sorted(names) == sorted(FAMILIES) and counts.min() > 0
    assert family_of("rep1_pair12_opp_dir0") == "pair12"
    with pytest.raises(ValueError, match="belongs to no family"):
        family_of("rep1_circle_dir0")


def test_bad_families_are_refused_before_any_fit(capsys: pytest.CaptureFixture[str]) -> None:
    from cr_nlp.cli.main import main

    with pytest.raises(ValueError, match="unknown family 'pairs'"):
        run_calibration_benchmark(families=("pairs",))
    with pytest.raises(ValueError, match="no subset"):
        run_calibration_benchmark(families=("seg",), history=True)
    assert main(["bench", "calibration", "--families", "seg,nope"]) == 2
    assert "--families: unknown family 'nope'" in capsys.readouterr().err
    with pytest.raises(ValueError, match="no history or axial compression folds"):
        run_calibration_benchmark(families=("seg",), model="cosserat",
                                  axial_compression="segments")
    assert main(["bench", "calibration", "--model", "cosserat", "--history"]) == 2
    assert "--model: model 'cosserat': no history" in capsys.readouterr().err
