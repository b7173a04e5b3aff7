"""The ``cr-nlp`` parser, built from the subcommand modules, and the entry point.

Adding a subcommand: a module ``cr_nlp/cli/<name>.py`` with ``add_parser(subparsers)``
(which sets ``run=<function(args) -> exit status>`` as a default) and one line in
``SUBCOMMANDS`` below. Shared input/output helpers live in ``_io.py``.
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
from collections.abc import Sequence

from . import (
    batch,
    bench,
    calibrate,
    demo,
    fk,
    follow,
    ik,
    plan,
    predict,
    show,
    statics,
    view,
    warmup,
)

SUBCOMMANDS = [
    fk,
    statics,
    ik,
    plan,
    follow,
    batch,
    calibrate,
    predict,
    show,
    view,
    bench,
    demo,
    warmup,
]
"""The subcommand modules, in ``--help`` order; each has ``add_parser(subparsers)``."""
FULL_EFFORT = ("bench", "batch", "view", "warmup")
"""Subcommands whose programs XLA optimises fully at once unless $CR_NLP_COMPILE says
otherwise (``cr_nlp._compile_effort``): benchmarks measure the code later runs get,
batches are large jobs, the viewer's live updates want the fastest code, a warm-up
compiles for later processes."""


def build_parser() -> argparse.ArgumentParser:
    """The ``cr-nlp`` argument parser with every subcommand."""
    parser = argparse.ArgumentParser(
        prog="cr-nlp",
        description="IK, trajectory planning and path following for tendon-driven continuum "
                    "robots (batched JAX search and refinement, exact CasADi/Ipopt polish).")
    sub = parser.add_subparsers(dest="command", required=True)
    for module in SUBCOMMANDS:
        module.add_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``cr-nlp`` with ``argv`` (default ``sys.argv[1:]``); returns the exit status
    (2 with a one-line message for bad input)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)  # --help ends here, having imported no JAX

    from .._compile_effort import setting as compile_setting
    from ..model import ModelFileError
    from ..runtime import configure, use_host_devices
    from ._io import UsageError

    args.command_line = shlex.join(["cr-nlp", *argv])  # what a report says it came from
    if args.command in FULL_EFFORT:
        os.environ.setdefault("CR_NLP_COMPILE", "full")
    try:
        compile_setting()  # a bad $CR_NLP_COMPILE is named before any work
    except ValueError as exc:
        print(f"cr-nlp {args.command}: error: {exc}", file=sys.stderr)
        return 2
    # Every core for the batched stages (before JAX starts); ``--devices`` where given.
    use_host_devices(getattr(args, "devices", None))
    configure()
    try:
        return args.run(args)
    except (UsageError, ModelFileError) as exc:
        print(f"cr-nlp {args.command}: error: {exc}", file=sys.stderr)
        return 2
