"""Stage retarget: ``data/scale_align`` -> ``data/retarget/<method>`` (see dexflow.stages.retarget).

Usage: ``python stages/retarget.py dexflow|position``; dvc.yaml runs both.
"""

import sys

from dexflow.pipeline.runner import stage_main
from dexflow.stages.retarget import STAGE

if __name__ == "__main__":
    sys.exit(stage_main(STAGE, sys.argv[1:]))
