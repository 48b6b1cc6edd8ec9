"""Stage metrics: every upstream stage's outputs -> ``reports/metrics/metrics.json`` (aggregates,
DVC metrics), ``data/metrics/sequences.csv`` (per sequence and method) and ``reports/plots/*.csv``
(per frame, DVC plots). Definitions: dexflow.stages.metrics."""

import sys

from dexflow.pipeline.runner import stage_main
from dexflow.stages.metrics import STAGE

if __name__ == "__main__":
    sys.exit(stage_main(STAGE, sys.argv[1:]))
