"""Stage track: ``data/refine`` + ``data/contact`` + ``data/scale_align`` -> ``data/track``.

Usage: ``python stages/track.py refine``; dvc.yaml runs it only with ``track=on`` (stage
``track@refine``; see dexflow.stages.track and dexflow.sim.track).
"""

import sys

from dexflow.pipeline.runner import stage_main
from dexflow.stages.track import STAGE

if __name__ == "__main__":
    sys.exit(stage_main(STAGE, sys.argv[1:]))
