"""``python -m pipeline.cli``: the ``codearcade`` command."""

import sys

from pipeline.cli import main

sys.exit(main())
