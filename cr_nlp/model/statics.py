"""Deprecated address of ``cr_nlp.model.cosserat`` (``solve_statics`` is on its face;
CHANGELOG 2026-12-02)."""

from .._moved import moved_module

moved_module(__name__, "cr_nlp.model.cosserat")
