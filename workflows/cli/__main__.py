"""``python -m workflows.cli``: the same as the ``pbmdem`` command."""

import sys

from workflows.cli.main import main

sys.exit(main())
