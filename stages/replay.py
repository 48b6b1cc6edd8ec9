"""Stage replay: a trajectory + ``data/contact`` + ``data/scale_align`` -> ``data/replay/<label>``.

Usage: ``python stages/replay.py baseline|retarget|refine``; dvc.yaml runs it for the baseline
(``data/retarget/position``), the retargeted (``data/retarget/dexflow``) and the refined
(``data/refine``) trajectories (see dexflow.replay and dexflow.io.layout).
"""

import sys

from dexflow.replay import STAGE
from dexflow.runner import stage_main

if __name__ == "__main__":
    sys.exit(stage_main(STAGE, sys.argv[1:]))
