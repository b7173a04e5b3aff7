"""``cr-nlp demo``: IK, planning and path following on the bundled defaults (``cr_nlp.demo``)."""

from __future__ import annotations

import argparse
import sys

from ..demo import TASKS


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``cr-nlp demo`` on the command's subparsers."""
    p = sub.add_parser("demo", help="IK, planning and path following on the bundled defaults")
    p.add_argument("--out", default="demo_output",
                   help="folder for results (JSON, CSV) and figures (PNG); default demo_output")
    p.add_argument("--penalty-only", action="store_true",
                   help="skip the exact Ipopt polish (faster, constraints only as penalties)")
    p.add_argument("--tasks", nargs="+", choices=list(TASKS), default=list(TASKS),
                   help="which tasks to run (default all three)")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Run the demo, print the summary table and the files written."""
    from ..demo import format_table, run_demo

    rows = run_demo(args.out, exact=not args.penalty_only, tasks=tuple(args.tasks),
                    progress=True)
    print(format_table(rows))
    print(f"\nfiles in {args.out}/: " + ", ".join(f for r in rows for f in r.files)
          + ", summary.md", file=sys.stderr)
    return 0
