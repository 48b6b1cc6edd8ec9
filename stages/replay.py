"""Stage replay: a trajectory + ``data/contact`` + ``data/scale_align`` -> ``data/replay/<label>``.

Usage: ``python stages/replay.py baseline|retarget|refine``; dvc.yaml runs it for the baseline
(``data/retarget/position``), the retargeted (``data/retarget/dexflow``) and the refined
(``data/refine``) trajectories (see dexflow.stages.replay and dexflow.io.layout).
"""

import sys

from dexflow.pipeline.runner import stage_main
from dexflow.stages.replay import STAGE

if __name__ == "__main__":
    sys.exit(stage_main(STAGE, sys.argv[1:]))
