"""Benchmark suites: each a command that prints a table (docs/design.md §4).

- ``ik``: ``cr-nlp bench ik`` (``run_ik_benchmark``), cr_nlp's IK against the baselines.
- ``baselines``: damped Newton–Raphson and a scipy derivative-free method, numpy in/out.
- ``_common``: the environment record and Markdown/CSV tables every benchmark shares.
- ``clearance``: ``cr-nlp bench clearance``, batched clearance throughput.
- ``suites``: the suites' names and sizes (light: the command's parser reads them).
- ``startup``: ``cr-nlp bench startup``, whole processes from a cold and a warm cache.

The command-line options live in ``cr_nlp.cli.bench`` (one shared set-up); every suite
writes its report through ``_common.write_report``.

Import the suite modules themselves (``cr_nlp.bench.ik``): this package imports nothing,
so that ``cr-nlp --help`` stays light.
"""
