"""Stage demo: generate the embedded demo dataset into ``data.root`` (see dexflow.data.demo)."""

import sys

from dexflow.data.demo import STAGE
from dexflow.runner import stage_main

if __name__ == "__main__":
    sys.exit(stage_main(STAGE, sys.argv[1:]))
