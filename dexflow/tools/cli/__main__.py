"""``python -m dexflow.tools.cli``: the ``dexflow`` command."""

import sys

from dexflow.tools.cli import main

sys.exit(main())
