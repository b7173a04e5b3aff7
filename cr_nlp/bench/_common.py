"""What every benchmark shares: the environment record, tables as Markdown and CSV, and
the one report writer (``write_report``).

A table is a list of row dicts and a list of ``Column``s that say which keys to show,
under which header, and how to format the numbers. Every table is printed and written
with the environment it was measured in (docs/design.md §4, "How to measure").
"""

from __future__ import annotations

import csv
import datetime
import json
import math
import os
import platform
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .._files import atomic_open

# ================================================================ the environment


def cpu_model() -> str:
    """The CPU's model name from /proc/cpuinfo (Linux), else what ``platform`` knows."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def usable_cores() -> int:
    """CPU cores this process may run on (its affinity mask, not the machine's count)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def environment() -> dict[str, str]:
    """Versions (python, jax, jaxlib, casadi, numpy, scipy), JAX backend and devices, CPU
    model and usable core count, JAX settings that change timings, the load average and
    the date: recorded with every table."""
    import casadi
    import jax
    import jaxlib
    import numpy
    import scipy

    cache = jax.config.jax_compilation_cache_dir
    return {
        "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "jaxlib": jaxlib.__version__,
        "casadi": casadi.__version__,
        "numpy": numpy.__version__,
        "scipy": scipy.__version__,
        "backend": jax.default_backend(),
        "devices": ", ".join(str(d) for d in jax.devices()),
        "cpu": cpu_model(),
        "cores": str(usable_cores()),
        "platform": platform.platform(),
        "jax_enable_x64": str(bool(jax.config.jax_enable_x64)),
        "jax compilation cache": cache if cache else "off",
        # Other work on the machine skews timings: say how busy it was.
        "load average (1, 5, 15 min)": ", ".join(f"{x:.2f}" for x in _load_average()),
    }


def _load_average() -> tuple[float, ...]:
    try:
        return os.getloadavg()
    except OSError:  # not available on this platform
        return (math.nan, math.nan, math.nan)


def environment_markdown(env: dict[str, str]) -> str:
    """The environment as a Markdown bullet list."""
    return "\n".join(f"- {key}: {value}" for key, value in env.items())


# ================================================================ tables


def format_number(value: Any, digits: int = 3) -> str:
    """A table cell: ``digits`` significant digits, "—" for None or NaN, text as is."""
    if value is None:
        return "—"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "—"
        if value == 0.0:
            return "0"
        if 1e-3 <= abs(value) < 1e5:
            text = f"{value:.{digits}g}"
            # %g switches to exponents at 10^digits; write such whole numbers out.
            return text if "e" not in text else f"{value:.0f}"
        return f"{value:.{max(digits - 1, 1)}e}"
    return str(value)


@dataclass(frozen=True)
class Column:
    """One column of a table: the row key, its header, and how to format a value."""

    key: str
    header: str
    format: Callable[[Any], str] = format_number


def fixed(decimals: int) -> Callable[[Any], str]:
    """A cell formatter with a fixed number of decimals ("—" for None/NaN)."""

    def fmt(value: Any) -> str:
        if value is None or (isinstance(value, float) and math.isnan(value)):
            return "—"
        return f"{float(value):.{decimals}f}"

    return fmt


def markdown_table(rows: Sequence[dict[str, Any]], columns: Sequence[Column]) -> str:
    """The rows as a GitHub Markdown table (numbers right-aligned)."""
    header = "| " + " | ".join(c.header for c in columns) + " |"
    align = "|" + "|".join("---:" if _numeric(rows, c.key) else "---" for c in columns) + "|"
    body = ["| " + " | ".join(c.format(row.get(c.key)) for c in columns) + " |" for row in rows]
    return "\n".join([header, align, *body])


def _numeric(rows: Sequence[dict[str, Any]], key: str) -> bool:
    values = [row.get(key) for row in rows if row.get(key) is not None]
    return bool(values) and all(isinstance(v, int | float) and not isinstance(v, bool)
                                for v in values)


def write_csv(rows: Sequence[dict[str, Any]], path: str | Path,
              keys: Sequence[str] | None = None) -> Path:
    """Write the rows as CSV with a header line (all keys of the rows in first-seen order
    unless ``keys`` is given); NaN and None become empty cells. Returns the path."""
    if keys is None:
        keys = list(dict.fromkeys(k for row in rows for k in row))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_open(path, newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(keys), extrasaction="ignore")
        writer.writeheader()
        for row in rows:
            writer.writerow({k: _csv_cell(row.get(k)) for k in keys})
    return path


def _csv_cell(value: Any) -> Any:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return ""
    if isinstance(value, float):
        return repr(value)  # round-trips exactly
    return value


def read_csv(path: str | Path) -> list[dict[str, str]]:
    """The rows of a CSV written by ``write_csv`` (values as strings)."""
    with Path(path).open(newline="") as f:
        return list(csv.DictReader(f))


def write_text(text: str, path: str | Path) -> Path:
    """Write ``text`` (ending with one newline) to ``path``, creating folders."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_open(path) as handle:
        handle.write(text.rstrip("\n") + "\n")
    return path


# ================================================================ the report


def write_report(name: str, report: str, out: str | Path | None,
                 tables: Mapping[str, Sequence[dict[str, Any]]] | None = None,
                 env: dict[str, str] | None = None, settings: dict[str, Any] | None = None,
                 csv_keys: Mapping[str, Sequence[str]] | None = None,
                 echo: bool = True) -> Path | None:
    """The one report writer of the benchmarks: print the Markdown ``report`` (with
    ``echo``) and, with an ``out`` folder, write ``<name>.md``, one ``<table>.csv`` per
    entry of ``tables`` (columns from ``csv_keys[table]`` where given) and
    ``environment.json`` (``{"environment": env, **settings}``). Returns the Markdown
    file's path, None without ``out``."""
    if echo:
        print(report)
    if out is None:
        return None
    out = Path(out)
    path = write_text(report, out / f"{name}.md")
    for table, rows in (tables or {}).items():
        write_csv(rows, out / f"{table}.csv", (csv_keys or {}).get(table))
    record = {"environment": env if env is not None else environment(), **(settings or {})}
    write_text(json.dumps(record, indent=2), out / "environment.json")
    return path


# ================================================================ docs/benchmarks.md


def section_markers(section: str) -> tuple[str, str]:
    """The HTML comments that open and close a benchmark's section in a Markdown file."""
    return f"<!-- cr-nlp bench: {section} -->", f"<!-- end cr-nlp bench: {section} -->"


def provenance_line(command: str, env: Mapping[str, str]) -> str:
    """One line saying where a table came from: the command, the UTC date, the versions
    (python, jax, casadi, numpy) and the device (JAX backend and devices, CPU model,
    usable cores, load average), from an ``environment()`` record."""
    get = env.get
    return (f"Written by `{command}` on {get('date', '?')}: Python {get('python', '?')}, "
            f"jax {get('jax', '?')}, casadi {get('casadi', '?')}, numpy {get('numpy', '?')}; "
            f"{get('backend', '?')} ({get('devices', '?')}), CPU {get('cpu', '?')}, "
            f"{get('cores', '?')} cores, load average "
            f"{get('load average (1, 5, 15 min)', '?')}.")


def _demote_headings(report: str) -> list[str]:
    """The report's lines with every Markdown heading two levels deeper (not in code):
    a report's title becomes a ``###`` section under the file's ``##`` task headings."""
    lines, in_code = [], False
    for line in report.strip("\n").splitlines():
        if line.startswith("```"):
            in_code = not in_code
        lines.append("##" + line if not in_code and line.startswith("#") else line)
    return lines


def replace_section(text: str, section: str, report: str, command: str,
                    env: Mapping[str, str]) -> str:
    """``text`` (a Markdown file's content) with the section ``section`` set to ``report``
    (headings two levels deeper, its title first, then the ``provenance_line``): the part
    between the section's markers is replaced, or the section is appended at the end.
    Everything outside the markers is kept as it is."""
    begin, end = section_markers(section)
    lines = _demote_headings(report)
    title = lines[:1] if lines and lines[0].startswith("###") else []
    rest = "\n".join(lines[len(title):]).strip("\n")
    body = "\n\n".join([*title, provenance_line(command, env), rest])
    block = f"{begin}\n{body}\n\n{end}"
    start = text.find(begin)
    if start < 0:
        return text.rstrip("\n") + ("\n\n" if text.strip() else "") + block + "\n"
    stop = text.find(end, start)
    if stop < 0:
        raise ValueError(f"the section {section!r} has its opening marker but no {end!r}")
    return text[:start] + block + text[stop + len(end):]


def publish_markdown(path: str | Path, section: str, report: str, command: str,
                     env: Mapping[str, str]) -> Path:
    """Write a benchmark's report into the Markdown file ``path`` (e.g. docs/benchmarks.md)
    as the section ``section`` (``replace_section``), creating the file if needed; the
    other sections stay. Returns the path."""
    path = Path(path)
    old = path.read_text() if path.exists() else ""
    return write_text(replace_section(old, section, report, command, env), path)
