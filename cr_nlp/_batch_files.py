"""What a batch job leaves in its folder (``cr_nlp.batch``): ``manifest.json`` (what the
job is and a log of its runs), one ``chunk_<id>.npz`` per finished chunk, and
``results.json``; writing each atomically, reading a chunk back, and the check that a
folder holds no other job, or the same job to resume, which the digests of its settings
and inputs decide (``digest``, ``solver_key``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import pickle
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from ._files import atomic_open, write_atomic

MANIFEST = "manifest.json"
RESULTS = "results.json"
MANIFEST_VERSION = 3
"""3: answers in the result protocol's field names (``tasks._result``, schema 1); 2: chunk
files hold arrays (``chunk_<id>.npz``); 1 held JSON rows."""


class BatchError(ValueError):
    """A job that cannot run as asked: a directory holding another job, a resume that
    does not match, chunks that failed after Dask's retries."""



def chunk_file(out_dir: str | Path, index: int) -> Path:
    """The file of chunk ``index`` in ``out_dir``."""
    return Path(out_dir) / f"chunk_{index:06d}.npz"


def chunk_ranges(count: int, chunk: int) -> list[tuple[int, int]]:
    """[start, stop) of each chunk of ``chunk`` problems covering ``count`` problems."""
    return [(s, min(s + chunk, count)) for s in range(0, count, chunk)]


def write_json(path: Path, data: Any, sync: bool = True) -> None:
    """Write JSON so that ``path`` is either its old content or the complete new one
    (``sync=False`` skips the fsync: a power cut may then lose it).

    Compact: ``json`` encodes in C only without ``indent`` (1000 IK rows: ~15 ms
    instead of ~170 ms)."""
    write_atomic(path, json.dumps(data).encode() + b"\n", sync)


_CHUNK_META = ("chunk", "start", "stop", "run", "worker", "pid", "seconds", "timing")


def write_chunk(path: Path, record: dict[str, Any]) -> None:
    """Write a chunk's record (``solve_chunk``'s, with start, stop and run) atomically:
    its metadata (and planning rows) as JSON text, the IK columns as arrays."""
    meta = {k: record[k] for k in _CHUNK_META if k in record}
    if "rows" in record:
        meta["rows"] = record["rows"]
    arrays = {f"column_{k}": v for k, v in record.get("columns", {}).items()}
    with atomic_open(path, "wb") as handle:
        np.savez(handle, meta=json.dumps(meta), **arrays)


def read_chunk(path: str | Path) -> dict[str, Any] | None:
    """A chunk file's record (``write_chunk``), None if it is absent or unreadable (then
    the chunk is solved again)."""
    try:
        with np.load(path, allow_pickle=False) as data:
            record = json.loads(str(data["meta"]))
            columns = {k[len("column_"):]: data[k] for k in data.files if k.startswith("column_")}
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
        return None
    if not isinstance(record, dict) or not ({"chunk", "start", "stop"} <= record.keys()):
        return None
    if columns:
        record["columns"] = columns
    count = record["stop"] - record["start"]
    answers = columns.get("success") if columns else record.get("rows")
    return record if answers is not None and len(answers) == count else None



def open_manifest(
    out: Path, job: dict[str, Any], chunk: int | None, resume: bool
) -> dict[str, Any] | None:
    """The manifest of a job to resume (checked against ``job``), or None for a new job
    (after checking that ``out`` holds no other job)."""
    path = out / MANIFEST
    if not path.exists():
        if any(out.glob("chunk_*")):
            raise BatchError(
                f"{out} holds chunk files but no {MANIFEST}: not a batch job "
                f"this version can resume; use an empty directory"
            )
        return None
    if not resume:
        raise BatchError(
            f"{out} already holds a batch job ({MANIFEST}); rerun with "
            f"--resume (resume=True) to finish it, or use another directory"
        )
    try:
        manifest = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise BatchError(f"{path} is unreadable ({exc}); use another directory") from None
    differ = [
        f"{k}: {manifest.get(k)!r} in the manifest, {v!r} now"
        for k, v in job.items()
        if manifest.get(k) != v
    ]
    if chunk is not None and manifest.get("chunk") != chunk:
        differ.append(f"chunk: {manifest.get('chunk')!r} in the manifest, {chunk!r} now")
    if differ:
        raise BatchError(f"cannot resume {out}: it holds another job (" + "; ".join(differ) + ")")
    return manifest


def read_chunks(out: Path, manifest: dict[str, Any]) -> tuple[list[dict[str, Any]],
                                                              dict[str, float]]:
    """Every chunk's record (``read_chunk``), in input order, and the worker seconds per
    stage summed over them (their ``total`` left out); ``BatchError`` if one is missing
    or damaged."""
    records = []
    timing: dict[str, float] = {}
    for i, (start, stop) in enumerate(chunk_ranges(manifest["count"], manifest["chunk"])):
        record = read_chunk(chunk_file(out, i))
        if record is None or (record["start"], record["stop"]) != (start, stop):
            raise BatchError(f"chunk {i} is missing or damaged in {out}; rerun with --resume")
        records.append(record)
        for key, value in record.get("timing", {}).items():
            if key != "total":
                timing[key] = timing.get(key, 0.0) + float(value)
    return records, timing


# ================================================================ which job it is


def digest(value: Any) -> str:
    """A sha256 hex digest of ``value``'s bytes (or its pickle)."""
    return hashlib.sha256(value if isinstance(value, bytes) else pickle.dumps(value)).hexdigest()


def solver_key(kind: str, robot: Any, scene: Any, config: Any) -> str:
    """The worker's solver cache key of a job: a digest of its kind, robot, scene and
    solver settings (the file each was read from left out)."""
    return digest((kind, _without_source(robot), _without_source(scene), config))


def _without_source(obj: Any) -> Any:
    """The robot or scene without the path it was read from (a bundled name and the same
    file are the same job)."""
    if dataclasses.is_dataclass(obj) and any(f.name == "source" for f in dataclasses.fields(obj)):
        return dataclasses.replace(obj, source="")
    return obj


def plain_rows(rows: Any) -> Any:
    """Rows as JSON-able lists of floats, or their repr where they are not numeric."""
    return [np.asarray(r, float).tolist() if _numeric(r) else repr(r) for r in rows]


def _numeric(row: Any) -> bool:
    try:
        np.asarray(row, float)
    except (TypeError, ValueError):
        return False
    return True
