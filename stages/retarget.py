"""Stage retarget: ``data/scale_align`` -> ``data/retarget/<method>`` (see dexflow.retarget).

Usage: ``python stages/retarget.py dexflow|position``; dvc.yaml runs both.
"""

from __future__ import annotations

import logging
import sys

from dexflow.config import load_params
from dexflow.io.atomic import save_json
from dexflow.retarget import run_retarget


def main(argv: list[str]) -> int:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    method = argv[0] if argv else "dexflow"
    params = load_params("params.yaml")
    summary = run_retarget(params, method, "data/scale_align", f"data/retarget/{method}")
    fps = summary["num_frames"] / summary["seconds"] if summary["seconds"] else float("nan")
    keys = (
        "num_sequences",
        "num_ok",
        "num_failed",
        "num_frames",
        "keypoint_error_mm",
        "rms_joint_acc",
        "velocity_kl",
        "keypoint_error_gt_mm",
        "velocity_kl_gt",
    )
    metrics = {k: summary[k] for k in keys if k in summary}
    save_json(f"reports/metrics/retarget_{method}.json", metrics)
    save_json(f"reports/timing/retarget_{method}.json", {"frames_per_second": fps})  # wall clock
    logging.info(
        "retarget %s: %d/%d sequences ok, %d frames, %.1f frames/s, error %.2f mm, "
        "RMS joint acc %.2f rad/s^2, velocity KL %.3f",
        method,
        summary["num_ok"],
        summary["num_sequences"],
        summary["num_frames"],
        fps,
        summary["keypoint_error_mm"],
        summary["rms_joint_acc"],
        summary["velocity_kl"],
    )
    for name, entry in summary["sequences"].items():
        if entry["status"] != "ok":
            logging.error("retarget %s: %s failed: %s", method, name, entry["error"])
    return 0 if summary["num_ok"] > 0 else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
