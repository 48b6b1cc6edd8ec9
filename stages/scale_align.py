"""Stage scale_align: ``data.root`` -> ``data/scale_align`` (see dexflow.stages.scale_align)."""

import sys

from dexflow.pipeline.runner import stage_main
from dexflow.stages.scale_align import STAGE

if __name__ == "__main__":
    sys.exit(stage_main(STAGE, sys.argv[1:]))
