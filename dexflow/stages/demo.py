"""Stage demo: the embedded demo dataset, generated into ``data.root``.

The generator is :func:`dexflow.data.demo.generate_demo` (what the demo holds and why: its
module docstring); this stage runs it from scratch with the ``demo`` params and draws
``reports/figures/demo.png``.
"""

from __future__ import annotations

import shutil

from dexflow.data.demo import FIGURE_OBJECTS, generate_demo
from dexflow.io.layout import Layout
from dexflow.params import PipelineParams
from dexflow.pipeline.runner import StageSpec

__all__ = ["STAGE", "run_demo"]


def run_demo(params: PipelineParams, layout: Layout) -> dict:
    """Stage runner: generate the demo into ``layout.data`` (from scratch) and draw
    ``reports/figures/demo.png``.

    Returns:
        The stage's metrics: ``objects``, ``sequences``, ``frames`` and the frames of each kind of
        annotation fault (``dropout_frames``, ``tracking_lost_frames``, ``template_frames``).
    """
    from dexflow.plots import plot_sequence_frames

    out = layout.data.root
    if out.exists():
        shutil.rmtree(out)
    manifest = generate_demo(params.demo, out, params.run)
    entries = manifest["sequences"]
    names = [e["name"] for e in entries]
    shown = [n for n in names if n.split("__")[0] in FIGURE_OBJECTS] or names
    plot_sequence_frames(out, shown[:: max(1, len(shown) // 6)][:6], layout.figures / "demo.png")
    return {
        "objects": len(manifest["objects"]),
        "sequences": manifest["num_sequences"],
        "frames": manifest["num_frames"],
        "dropout_frames": sum(e["dropout_frames"] for e in entries),
        "tracking_lost_frames": sum(e["tracking_lost_frames"] for e in entries),
        "template_frames": sum(e["template_frames"] for e in entries),
    }


STAGE = StageSpec(
    name="demo",
    run=run_demo,
    metric_keys=(
        "objects",
        "sequences",
        "frames",
        "dropout_frames",
        "tracking_lost_frames",
        "template_frames",
    ),
    describe=lambda s: f"{s['sequences']} sequences, {s['frames']} frames, {s['objects']} objects",
)
