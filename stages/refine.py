"""Stage refine: retargeted ``q`` + contacts -> ``data/refine`` (see dexflow.stages.refine)."""

import sys

from dexflow.pipeline.runner import stage_main
from dexflow.stages.refine import STAGE

if __name__ == "__main__":
    sys.exit(stage_main(STAGE, sys.argv[1:]))
