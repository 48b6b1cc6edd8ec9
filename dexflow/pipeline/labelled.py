"""What the stages run on every labelled trajectory (simulate, replay) share: their resumable
output and the inputs of one sequence."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from dexflow.hands.files import staged_spec
from dexflow.hands.robot import RobotHand, cached_hand
from dexflow.io.artifacts import ContactResult, read_contact, read_trajectory
from dexflow.io.layout import Layout, StageDir
from dexflow.io.sequence import Sequence, load_sequence
from dexflow.params import PipelineParams
from dexflow.pipeline.resume import StageOutput

__all__ = ["labelled_hand", "labelled_output", "load_labelled"]


def labelled_output(
    name: str, params: PipelineParams, layout: Layout, label: str, out: StageDir
) -> StageOutput:
    """The output of stage ``name`` on the trajectories labelled ``label``: resumed on the hand
    and the stage's own params section, its inputs the trajectories, contacts, scaled scene and
    hand model.

    Raises:
        HandConfigError: ``data/hand`` holds no copy of the hand model, or another model's.
    """
    staged_spec(params.hand, layout.hand_files.root)  # fail the stage, not every sequence
    return StageOutput(
        out,
        f"{name} {label}",
        {"hand": params.hand, name: getattr(params, name)},
        inputs=(layout.trajectory(label), layout.contact, layout.scale_align, layout.hand_files),
    )


def labelled_hand(params: PipelineParams, layout: Layout) -> RobotHand:
    """The hand, loaded from stage hand's copy (once per process)."""
    return cached_hand(staged_spec(params.hand, layout.hand_files.root), None)


def load_labelled(
    params: PipelineParams, layout: Layout, path: Path
) -> tuple[RobotHand, Sequence, np.ndarray, ContactResult]:
    """One sequence's hand, scaled sequence, trajectory ``q (T, dof)`` (``path``) and contacts,
    in a worker limited to one torch thread."""
    torch.set_num_threads(1)
    hand = labelled_hand(params, layout)
    aligned = layout.scale_align
    seq = load_sequence(aligned.sequence(path), data_root=aligned.root)
    q = read_trajectory(path, hand.joint_names, frames=seq.num_frames).q
    found = read_contact(layout.contact.sequence(path), list(hand.spec.fingers), seq.num_frames)
    return hand, seq, q, found
