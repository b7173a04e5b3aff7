"""Deprecated address of ``cr_nlp.model.history`` (CHANGELOG 2026-12-02)."""

from .._moved import moved_module

moved_module(__name__, "cr_nlp.model.history")
