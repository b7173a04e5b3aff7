"""The ``cr-nlp`` command: one module per subcommand, each a thin front end to the library.

``main.py`` builds the parser from the subcommand modules listed in ``main.SUBCOMMANDS``
(``fk``, ``statics``, ``ik``, ``plan``, ``follow``, ``batch``, ``calibrate``, ``predict``,
``show``, ``view``, ``bench``, ``demo``, ``warmup``; ``ik``, ``plan`` and ``follow`` hand
``--model cosserat`` to ``_tension_ik``, ``_tension_plan`` and ``_tension_follow``); ``_io.py``
holds what they share (``UsageError``, number and JSON input/output, the resolver of
file-or-bundled-name arguments) and imports none of them.
"""

from ._io import UsageError as UsageError
from .main import build_parser as build_parser
from .main import main as main
