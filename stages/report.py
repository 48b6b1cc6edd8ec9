"""Stage report: metrics -> ``reports/summary.md`` and its figures (see dexflow.report)."""

import sys

from dexflow.report import STAGE
from dexflow.runner import stage_main

if __name__ == "__main__":
    sys.exit(stage_main(STAGE, sys.argv[1:]))
