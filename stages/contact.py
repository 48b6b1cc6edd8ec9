"""Stage contact: ``data/retarget/dexflow`` + ``data/scale_align`` -> ``data/contact``."""

from __future__ import annotations

import logging
import sys

from dexflow.config import load_params
from dexflow.contact import run_contact
from dexflow.io.atomic import save_json

TIMING = "reports/timing/contact.json"  # wall clock: kept out of the deterministic metrics

KEYS = ("num_sequences", "num_ok", "num_failed", "num_frames", "fluctuation_removed",
        "fluctuation_removed_vs_threshold", "changes_per_finger_s_raw", "changes_per_finger_s_final",
        "raw_vs_truth", "final_vs_truth")  # fmt: skip


def main() -> int:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    params = load_params("params.yaml")
    summary = run_contact(params, "data/retarget/dexflow", "data/scale_align", "data/contact")
    fps = summary["num_frames"] / summary["seconds"] if summary["seconds"] else float("nan")
    metrics = {k: summary[k] for k in KEYS if k in summary}
    save_json("reports/metrics/contact.json", metrics)
    save_json(TIMING, {"frames_per_second": fps})
    f1_raw = summary.get("raw_vs_truth", {}).get("f1", float("nan"))
    f1_final = summary.get("final_vs_truth", {}).get("f1", float("nan"))
    logging.info(
        "contact: %d/%d sequences; fluctuations removed: %.0f %% of raw (hysteresis) states, "
        "%.0f %% of single-threshold states; %.2f -> %.2f changes per finger per second; "
        "F1 %.3f -> %.3f",
        summary["num_ok"], summary["num_sequences"], 100 * summary["fluctuation_removed"],
        100 * summary["fluctuation_removed_vs_threshold"], summary["changes_per_finger_s_raw"],
        summary["changes_per_finger_s_final"], f1_raw, f1_final,
    )  # fmt: skip
    for name, entry in summary["sequences"].items():
        if entry["status"] != "ok":
            logging.error("contact: %s failed: %s", name, entry["error"])
    return 0 if summary["num_ok"] > 0 else 1


if __name__ == "__main__":
    sys.exit(main())
