"""Stage scale_align: ``data.root`` -> ``data/scale_align`` (see dexflow.align)."""

from __future__ import annotations

import logging
import sys

from dexflow.align import run_scale_align
from dexflow.config import load_params
from dexflow.io.atomic import save_json

OUT = "data/scale_align"
METRICS = "reports/metrics/scale_align.json"


def main() -> int:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    params = load_params("params.yaml")
    summary = run_scale_align(params, params.data.root, OUT)
    save_json(
        METRICS,
        {k: summary[k] for k in ("num_sequences", "num_ok", "num_failed", "num_frames")}
        | {"num_objects": len(summary["objects"])},
    )
    logging.info(
        "scale_align: %d/%d sequences ok, %d frames (summary: %s/summary.json)",
        summary["num_ok"],
        summary["num_sequences"],
        summary["num_frames"],
        OUT,
    )
    for name, entry in summary["sequences"].items():
        if entry["status"] != "ok":
            logging.error("scale_align: %s failed: %s", name, entry["error"])
    return 0 if summary["num_ok"] > 0 else 1


if __name__ == "__main__":
    sys.exit(main())
