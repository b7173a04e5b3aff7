"""Benchmark suites: each a command that prints a table (docs/design.md §4).

- ``ik``: ``cr-nlp bench ik`` (``run_ik_benchmark``), cr_nlp's IK against the baselines.
- ``baselines``: damped Newton–Raphson and a scipy derivative-free method, numpy in/out.
- ``common``: the environment record and Markdown/CSV tables every benchmark shares.
- ``clearance``: ``cr-nlp bench clearance``, batched clearance throughput.

The command-line options live in ``cr_nlp.cli.bench`` (one shared set-up); every suite
writes its report through ``common.write_report``.
"""

from ._baselines import BaselineSolve as BaselineSolve
from ._baselines import DampedNewtonConfig as DampedNewtonConfig
from ._baselines import ScipyConfig as ScipyConfig
from ._baselines import damped_newton_ik as damped_newton_ik
from ._baselines import scipy_ik as scipy_ik
from ._common import Column as Column
from ._common import environment as environment
from ._common import markdown_table as markdown_table
from ._common import write_csv as write_csv
from ._common import write_report as write_report
from .ik import IKBenchSizes as IKBenchSizes
from .ik import run_ik_benchmark as run_ik_benchmark
