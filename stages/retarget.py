"""Stage retarget: ``data/scale_align`` -> ``data/retarget/<method>`` (see dexflow.retarget).

Usage: ``python stages/retarget.py dexflow|position``; dvc.yaml runs both.
"""

import sys

from dexflow.retarget import STAGE
from dexflow.runner import stage_main

if __name__ == "__main__":
    sys.exit(stage_main(STAGE, sys.argv[1:]))
