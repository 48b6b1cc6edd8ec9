"""Stage report: metrics -> ``reports/summary.md`` and ``reports/figures/summary_*.png``."""

from __future__ import annotations

import logging
import sys

from dexflow.config import load_params
from dexflow.io.layout import Layout
from dexflow.report import write_project_summary


def main() -> int:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    params = load_params("params.yaml")
    out = write_project_summary(Layout.of(params.data.root), data_name=params.data.name)
    logging.info("report: wrote %s", out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
