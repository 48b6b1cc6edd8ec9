"""Stage hand: the hand model and the files it reads -> ``data/hand/`` (see dexflow.stages.hand)."""

import sys

from dexflow.pipeline.runner import stage_main
from dexflow.stages.hand import STAGE

if __name__ == "__main__":
    sys.exit(stage_main(STAGE, sys.argv[1:]))
