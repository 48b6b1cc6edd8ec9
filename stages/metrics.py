"""Stage metrics: every upstream stage's outputs -> ``reports/metrics/metrics.json`` (aggregates,
DVC metrics), ``data/metrics/sequences.csv`` (per sequence and method) and ``reports/plots/*.csv``
(per frame, DVC plots). Definitions: dexflow.metrics."""

import sys

from dexflow.metrics import STAGE
from dexflow.runner import stage_main

if __name__ == "__main__":
    sys.exit(stage_main(STAGE, sys.argv[1:]))
