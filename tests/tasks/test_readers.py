"""``tasks.readers``: every input file a task reads, one reader each, and one error type
(``InputFileError``, a ``ValueError``) for a file that is missing, not JSON/CSV or not of
its format, naming the file."""

from __future__ import annotations

import warnings

import pytest

from cr_nlp._files import InputFileError
from cr_nlp.model import load_robot
from cr_nlp.tasks import readers

RAO = load_robot("tdcr2_rao2021")


def _readers(path):
    return {
        "targets": lambda: readers.read_targets(path),
        "problems": lambda: readers.read_problems(path),
        "tension problems": lambda: readers.read_tension_problems(RAO, path),
        "path": lambda: readers.load_path(path),
        "recording": lambda: readers.read_measurements(path, 6),
    }


@pytest.mark.parametrize("content", [None, b"{not json", b"\xff\xfe", b"[1, 2]"],
                         ids=["missing", "not-json", "not-utf8", "wrong-shape"])
def test_every_reader_names_the_file_in_one_error_type(tmp_path, content) -> None:
    file = tmp_path / "input.json"
    if content is not None:
        file.write_bytes(content)
    for what, read in _readers(file).items():
        with pytest.raises(InputFileError) as caught:
            read()
        assert str(file) in str(caught.value), (what, str(caught.value))
        assert isinstance(caught.value, ValueError)


def test_a_problem_entry_names_its_index_and_key(tmp_path) -> None:
    file = tmp_path / "p.json"
    file.write_text('{"problems": [{"start": [0, 0, 0, 0, 0, 0], "goal": [0, 0, 0, 0, 0, 0]},'
                    ' {"start": [0, 0, 0, 0, 0, 0], "aim": 1}]}')
    with pytest.raises(InputFileError, match=r"problem 1: unknown key 'aim'"):
        readers.read_tension_problems(RAO, file)
    file.write_text('{"problems": [{"start": [0, 0], "goal": [1, 1]}], "horizon": 1}')
    with pytest.raises(InputFileError, match=r"field 'horizon': must be an integer from 2"):
        readers.read_problems(file)


def test_the_old_addresses_warn_and_return_the_same_reader() -> None:
    from cr_nlp.tasks import paths
    from cr_nlp.tasks.calibration import measurements

    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        assert paths.load_path is readers.load_path
        assert measurements.read_measurements is readers.read_measurements
    assert [w.category for w in seen] == [DeprecationWarning] * 2
    assert "cr_nlp.tasks.readers.load_path" in str(seen[0].message)
    with pytest.raises(AttributeError):
        paths.no_such_name  # noqa: B018
