"""Stage metrics: every upstream stage's outputs -> ``reports/metrics/metrics.json`` (aggregates,
DVC metrics), ``data/metrics/sequences.csv`` (per sequence and method) and ``reports/plots/*.csv``
(per frame, DVC plots). Definitions: dexflow.metrics."""

from __future__ import annotations

import logging
import sys

from dexflow.config import load_params
from dexflow.io.atomic import save_json
from dexflow.metrics import run_metrics

ROOTS = {
    "scale_align": "data/scale_align",
    "contact": "data/contact",
    "baseline": "data/retarget/position",
    "retarget": "data/retarget/dexflow",
    "refine": "data/refine",
    "simulate": "data/simulate",
}


def main() -> int:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    params = load_params("params.yaml")
    summary = run_metrics(params, ROOTS, "data/metrics", "reports/plots")
    sequences = summary.pop("sequences")  # data/metrics/summary.json holds them
    save_json("reports/metrics/metrics.json", summary)
    for method in ("baseline", "retarget", "refine"):
        logging.info(
            "metrics %s: error %.2f mm, SSR %.1f %%, PD %.2f mm, CD %.2f mm, SPD %.2f mm, FVR %.3f, "
            "velocity KL %.3f, RMS acc %.2f rad/s^2, time-aligned CD %.2f mm",
            method, *(summary.get(f"{method}.{k}", float("nan")) for k in (
                "keypoint_error_mm", "ssr", "pd_mm", "cd_mm", "spd_mm", "fvr", "velocity_kl",
                "rms_acc", "time_aligned_cd_mm")),
        )  # fmt: skip
    for name, entry in sequences.items():
        if entry["status"] != "ok":
            logging.error("metrics: %s failed: %s", name, entry["error"])
    return 0 if summary["num_failed"] < summary["num_sequences"] else 1


if __name__ == "__main__":
    sys.exit(main())
