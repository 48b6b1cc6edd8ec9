"""Stage scale_align: ``data.root`` -> ``data/scale_align`` (see dexflow.align)."""

import sys

from dexflow.align import STAGE
from dexflow.runner import stage_main

if __name__ == "__main__":
    sys.exit(stage_main(STAGE, sys.argv[1:]))
