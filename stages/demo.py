"""Stage demo: generate the embedded demo dataset into ``data/demo`` (params.yaml ``demo``)."""

from __future__ import annotations

import logging
import shutil
import sys

from dexflow.config import load_params
from dexflow.data.demo import generate_demo
from dexflow.io.atomic import save_json
from dexflow.io.layout import Layout
from dexflow.plots import plot_sequence_frames

FIGURE_OBJECTS = (
    "025_mug",
    "024_bowl",
    "011_banana",
    "005_tomato_soup_can",
    "051_large_clamp",
    "006_mustard_bottle",
)


def main() -> int:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    params = load_params("params.yaml")
    layout = Layout.of(params.data.root)
    out = layout.data.root
    if out.exists():
        shutil.rmtree(out)
    manifest = generate_demo(params.demo, out, params.run)
    entries = manifest["sequences"]
    save_json(
        layout.stage_metrics("demo"),
        {
            "objects": len(manifest["objects"]),
            "sequences": manifest["num_sequences"],
            "frames": manifest["num_frames"],
            "dropout_frames": sum(e["dropout_frames"] for e in entries),
            "tracking_lost_frames": sum(e["tracking_lost_frames"] for e in entries),
            "template_frames": sum(e["template_frames"] for e in entries),
        },
    )
    names = [e["name"] for e in entries]
    shown = [n for n in names if n.split("__")[0] in FIGURE_OBJECTS] or names
    plot_sequence_frames(out, shown[:: max(1, len(shown) // 6)][:6], layout.figures / "demo.png")
    logging.info(
        "demo: %d sequences, %d frames in %s",
        manifest["num_sequences"],
        manifest["num_frames"],
        out,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
