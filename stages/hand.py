"""Stage hand: the hand model and the files it reads -> ``data/hand/`` (see dexflow.hand_stage)."""

import sys

from dexflow.hand_stage import STAGE
from dexflow.runner import stage_main

if __name__ == "__main__":
    sys.exit(stage_main(STAGE, sys.argv[1:]))
