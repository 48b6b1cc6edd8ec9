"""Stage hand: copy the hand's model file and every file it reads into ``data/hand/``.

A hand yaml may name a model anywhere: inside dexflow (``pkg://dexflow/...``), inside another
installed package, or a file of the user's. DVC sees none of these, so editing a model (a joint
limit, a mesh) would leave ``dvc status`` clean and the trajectories stale. This stage is
``always_changed`` in ``dvc.yaml``: every ``dvc repro`` runs it (well under a second: it only
reads and copies the files), and DVC reruns the stages downstream exactly when the copy's bytes
changed. Those stages load the hand from the copy (:func:`dexflow.hands.files.staged_spec`), so
what they read is what DVC hashed.
"""

from __future__ import annotations

from dexflow.errors import HandConfigError
from dexflow.hands.files import copy_model
from dexflow.io.layout import Layout
from dexflow.params import PipelineParams
from dexflow.pipeline.runner import StageSpec

__all__ = ["STAGE", "run_hand"]


def run_hand(params: PipelineParams, layout: Layout) -> dict:
    """Stage runner: ``params.hand.model`` (resolved as the stages resolve it) and the files it
    reads -> ``layout.hand_files``.

    Returns:
        The record written to ``hand.json`` (no timing: there is nothing to time).

    Raises:
        HandConfigError: the model or a file it names is missing or unreadable.
    """
    record = copy_model(params.hand.model, layout.hand_dir, layout.hand_files.root)
    copied = layout.hand_files.root / record["model"]
    if copied.suffix.lower() != ".urdf":  # a URDF's files are its meshes, all found above
        import mujoco

        try:
            mujoco.MjModel.from_xml_path(str(copied))
        except ValueError as exc:
            raise HandConfigError(
                f"hand model '{params.hand.model}': its copy in {layout.hand_files.root} does not "
                f"compile (a file it reads that dexflow.hands.files does not list?): {exc}"
            ) from exc
    return record


STAGE = StageSpec(
    name="hand",
    run=run_hand,
    metric_keys=(),  # a copy, not a measurement
    describe=lambda s: f"copied {s['model']} and {len(s['files']) - 1} file(s) it reads",
)
