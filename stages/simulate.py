"""Stage simulate: a trajectory + ``data/contact`` + ``data/scale_align`` -> ``data/simulate/<label>``.

Usage: ``python stages/simulate.py baseline|retarget|refine``; dvc.yaml runs it for the baseline
(``data/retarget/position``), the retargeted (``data/retarget/dexflow``) and the refined
(``data/refine``) trajectories (see dexflow.stages.simulate and dexflow.io.layout).
"""

import sys

from dexflow.pipeline.runner import stage_main
from dexflow.stages.simulate import STAGE

if __name__ == "__main__":
    sys.exit(stage_main(STAGE, sys.argv[1:]))
