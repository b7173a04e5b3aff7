"""``python -m cr_nlp.cli``: the same as ``cr-nlp``."""

import sys

from .main import main

sys.exit(main())
