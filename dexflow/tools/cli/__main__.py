"""``python -m dexflow.tools.cli`` runs the ``dexflow`` command (:func:`dexflow.tools.cli.main`)."""

import sys

from dexflow.tools.cli import main

sys.exit(main())
