"""Stage report: metrics -> ``reports/summary.md`` and its figures (see dexflow.stages.report)."""

import sys

from dexflow.pipeline.runner import stage_main
from dexflow.stages.report import STAGE

if __name__ == "__main__":
    sys.exit(stage_main(STAGE, sys.argv[1:]))
