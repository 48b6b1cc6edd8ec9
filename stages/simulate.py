"""Stage simulate: a trajectory + ``data/contact`` + ``data/scale_align`` -> ``data/simulate/<label>``.

Usage: ``python stages/simulate.py LABEL TRAJECTORY_DIR``; dvc.yaml runs it for the baseline
(``data/retarget/position``), the retargeted (``data/retarget/dexflow``) and the refined
(``data/refine``) trajectories (see dexflow.simulate).
"""

from __future__ import annotations

import logging
import sys

from dexflow.config import load_params
from dexflow.io.atomic import save_json
from dexflow.simulate import run_simulate

KEYS = ("num_sequences", "num_ok", "num_failed", "frames_evaluated", "ssr", "ssr_bench", "ssr_raw",
        "ssr_bench_raw", "penetration_mean_mm", "over_tolerance", "parts_penetration_mean_mm",
        "parts_over_tolerance")  # fmt: skip


def main(argv: list[str]) -> int:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    if len(argv) != 2:
        logging.error("usage: python stages/simulate.py LABEL TRAJECTORY_DIR")
        return 2
    label, trajectories = argv
    params = load_params("params.yaml")
    summary = run_simulate(
        params, label, trajectories, "data/contact", "data/scale_align", f"data/simulate/{label}"
    )
    save_json(f"reports/metrics/simulate_{label}.json", {k: summary[k] for k in KEYS})
    save_json(  # wall clock: kept out of the deterministic metrics
        f"reports/timing/simulate_{label}.json",
        {"frames_per_second_one_core": summary["frames_per_second_one_core"]},
    )
    logging.info(
        "simulate %s: %d/%d sequences; SSR %.1f %% (contact), %.1f %% (DexGraspBench); without "
        "the penetration tolerance %.1f %% / %.1f %%; %d frames, mean starting penetration "
        "%.2f mm; %.2f frames/s per core",
        label, summary["num_ok"], summary["num_sequences"], summary["ssr"], summary["ssr_bench"],
        summary["ssr_raw"], summary["ssr_bench_raw"], summary["frames_evaluated"],
        summary["penetration_mean_mm"], summary["frames_per_second_one_core"],
    )  # fmt: skip
    for name, entry in summary["sequences"].items():
        if entry["status"] != "ok":
            logging.error("simulate %s: %s failed: %s", label, name, entry["error"])
    return 0 if summary["num_ok"] > 0 else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
