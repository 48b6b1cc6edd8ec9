"""Stage contact: ``data/retarget/dexflow`` + ``data/scale_align`` -> ``data/contact``."""

import sys

from dexflow.pipeline.runner import stage_main
from dexflow.stages.contact import STAGE

if __name__ == "__main__":
    sys.exit(stage_main(STAGE, sys.argv[1:]))
