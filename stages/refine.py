"""Stage refine: retargeted ``q`` + contacts -> ``data/refine`` (see dexflow.refine)."""

import sys

from dexflow.refine import STAGE
from dexflow.runner import stage_main

if __name__ == "__main__":
    sys.exit(stage_main(STAGE, sys.argv[1:]))
