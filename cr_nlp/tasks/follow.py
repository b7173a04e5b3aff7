"""Deprecated address of ``cr_nlp.tasks.geometry.follow`` (CHANGELOG 2026-12-02)."""

from .._moved import moved_module

moved_module(__name__, "cr_nlp.tasks.geometry.follow")
