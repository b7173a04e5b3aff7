"""Benchmark suites: each a command that prints a table (DESIGN.md §4)."""
