"""Stage report: metrics -> ``reports/summary.md`` and ``reports/figures/summary_*.png``."""

from __future__ import annotations

import logging
import sys

from dexflow.config import load_params
from dexflow.report import write_summary


def main() -> int:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    params = load_params("params.yaml")
    out = write_summary(
        "reports/metrics", "data/metrics/sequences.csv", "reports/plots", "reports/summary.md",
        "reports/figures", data_name=params.data.name,
    )  # fmt: skip
    logging.info("report: wrote %s", out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
