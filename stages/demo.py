"""Stage demo: generate the embedded demo dataset into ``data.root`` (see dexflow.data.demo)."""

import sys

from dexflow.pipeline.runner import stage_main
from dexflow.stages.demo import STAGE

if __name__ == "__main__":
    sys.exit(stage_main(STAGE, sys.argv[1:]))
