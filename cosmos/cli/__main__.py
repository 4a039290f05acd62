"""``python -m cosmos.cli``: the ``cosmos`` command."""

import sys

from cosmos.cli import main

sys.exit(main())
