"""Stage contact: ``data/retarget/dexflow`` + ``data/scale_align`` -> ``data/contact``."""

import sys

from dexflow.contact import STAGE
from dexflow.runner import stage_main

if __name__ == "__main__":
    sys.exit(stage_main(STAGE, sys.argv[1:]))
