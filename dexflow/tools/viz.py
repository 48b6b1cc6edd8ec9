"""Rerun recordings (``.rrd``) of a sequence: human keypoints, robot hand, object and contacts.

A recording is written headless (no viewer, no display) and holds, under the entity ``world``:

- ``world/human/keypoints`` and ``world/human/bones``: the 21 MANO-order keypoints and the
  five finger chains (wrist -> tip) per tracked frame; an empty row on frames with
  ``valid == False`` so that nothing stale is shown there.
- ``world/robot/<link>``: each collision link's mesh (in the link frame) logged once as static,
  and its link-to-world transform per frame. The links of a finger change colour with its
  contact state (green in contact, grey otherwise); ``world/robot/contacts`` adds one marker
  per finger at its outermost contact link in the same colours.
- ``world/object``: the object mesh, static, with its object-to-world pose per frame.

Every per-frame quantity goes in one ``send_columns`` call per entity, on two time lines:
``frame`` (the frame index) and ``time`` (seconds, from the sequence's timestamps or fps).
The recording id is derived from the sequence name and trajectory, and no wall-clock property
is written, so two recordings of the same inputs hold the same entities, rows and values (rerun
still stamps fresh row and chunk ids, so the bytes differ).
"""

from __future__ import annotations

import logging
import subprocess
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from dexflow.errors import DexflowError
from dexflow.hands.robot import RobotHand
from dexflow.human.keypoints import FINGER_KEYPOINTS, FINGERS, NUM_KEYPOINTS, WRIST
from dexflow.io.artifacts import ContactResult, read_contact, read_trajectory
from dexflow.io.layout import Layout
from dexflow.io.layout import project_root as find_project_root
from dexflow.io.sequence import Sequence, load_sequence

__all__ = [
    "HAND_BONES",
    "TRAJECTORIES",
    "MissingInputError",
    "RecordingInputs",
    "open_viewer",
    "record_sequence",
    "recording_id",
    "resolve_inputs",
    "write_recording",
]

log = logging.getLogger(__name__)

# Per finger, the keypoint chain drawn as one line strip: wrist, then the finger from the palm out.
HAND_BONES: tuple[tuple[int, ...], ...] = tuple((WRIST, *FINGER_KEYPOINTS[f]) for f in FINGERS)

# Trajectory choice (a label of dexflow.io.layout.TRAJECTORIES) -> the DVC stage that writes it.
TRAJECTORIES: dict[str, str] = {
    "refine": "refine",
    "retarget": "retarget@dexflow",
    "baseline": "retarget@position",
    "track": "track@refine",
}

_APPLICATION_ID = "dexflow"
_ID_NAMESPACE = uuid.UUID("6f1c8f2e-3d5b-4f7a-9a53-0d6c1e2b7a40")  # fixed: ids depend on names only
_RGBA = np.dtype(np.uint8)
_COLOR_CONTACT = (40, 200, 60, 255)
_COLOR_FREE = (150, 150, 150, 255)
_COLOR_LINK = (190, 190, 200, 255)
_COLOR_OBJECT = (90, 140, 220, 255)
_COLOR_KEYPOINTS = (240, 140, 40, 255)
_COLOR_BONES = (240, 180, 90, 255)
_KEYPOINT_RADIUS_M = 0.004
_BONE_RADIUS_M = 0.0015
_CONTACT_MARKER_RADIUS_M = 0.008


class MissingInputError(DexflowError, FileNotFoundError):
    """An upstream file a recording needs does not exist; the message names the stage."""


@dataclass(frozen=True)
class RecordingInputs:
    """The files one recording reads.

    Attributes:
        name: Sequence name (the file stem, e.g. ``025_mug__00_power``).
        sequence: The aligned sequence ``.npz``.
        data_root: Root its ``obj_mesh`` is relative to.
        trajectory: The ``.npz`` holding ``q (T, dof)`` and ``joint_names``.
        contact: The contact stage's ``.npz`` (may not exist).
    """

    name: str
    sequence: Path
    data_root: Path
    trajectory: Path
    contact: Path


def recording_id(name: str, trajectory: str) -> uuid.UUID:
    """A recording id that depends only on the sequence name and the trajectory choice."""
    return uuid.uuid5(_ID_NAMESPACE, f"{name}/{trajectory}")


def _require(path: Path, stage: str) -> Path:
    if not path.is_file():
        raise MissingInputError(
            f"{path}: no such file; it is written by the DVC stage '{stage}' "
            f"(run `dvc repro {stage}`)"
        )
    return path


def resolve_inputs(
    name_or_path: str | Path, trajectory: str = "refine", project_root: str | Path = "."
) -> RecordingInputs:
    """Find the files of one sequence in a project's outputs (:class:`Layout`).

    Args:
        name_or_path: A sequence name (``025_mug__00_power``) or the path of a sequence ``.npz``
            (its mesh is then looked up relative to the folder above its ``sequences/``).
        trajectory: ``refine``, ``retarget`` (DexFlow before refinement) or ``baseline``
            (the per-frame position retargeting).
        project_root: The project directory.

    Raises:
        ValueError: ``trajectory`` is not one of :data:`TRAJECTORIES`.
        MissingInputError: the sequence or trajectory file is missing (the message names the
            file and the stage that writes it). A missing contact file is not an error.
    """
    if trajectory not in TRAJECTORIES:
        raise ValueError(
            f"unknown trajectory {trajectory!r}; expected one of {', '.join(TRAJECTORIES)}"
        )
    layout = Layout(Path(project_root))
    text = str(name_or_path)
    if text.endswith(".npz") or Path(text).is_file():
        seq_path = Path(text)
        name = seq_path.stem
        data_root = (
            seq_path.parent.parent if seq_path.parent.name == "sequences" else seq_path.parent
        )
        if not seq_path.is_file():
            raise MissingInputError(f"{seq_path}: no such sequence file")
    else:
        name = text
        data_root = layout.scale_align.root
        seq_path = _require(layout.scale_align.sequence(name), "scale_align")
    traj_path = _require(layout.trajectory(trajectory).sequence(name), TRAJECTORIES[trajectory])
    return RecordingInputs(name, seq_path, data_root, traj_path, layout.contact.sequence(name))


def load_contact(path: str | Path, hand: RobotHand, num_frames: int) -> ContactResult | None:
    """Stage contact's result for a recording; None (and a warning) if the file is absent.

    Raises:
        ArtifactError: the file exists but does not fit the hand or the sequence.
    """
    path = Path(path)
    if not path.is_file():
        log.warning(
            "%s: no contact file (written by the DVC stage 'contact'); recording without "
            "contact colours",
            path,
        )
        return None
    return read_contact(path, list(hand.spec.fingers), num_frames)


def _entity(part: str) -> str:
    import rerun as rr

    return rr.escape_entity_path_part(part)


def _mesh3d(mesh: trimesh.Trimesh, color: tuple[int, ...] | None):
    """A static ``rr.Mesh3D`` with normals split at sharp edges (boxes stay flat-shaded)."""
    import rerun as rr

    shaded = mesh.smooth_shaded
    return rr.Mesh3D(
        vertex_positions=np.asarray(shaded.vertices, dtype=np.float32),
        triangle_indices=np.asarray(shaded.faces, dtype=np.uint32),
        vertex_normals=np.asarray(shaded.vertex_normals, dtype=np.float32),
        albedo_factor=color,
    )


def _time_columns(frames: np.ndarray, seconds: np.ndarray) -> list:
    import rerun as rr

    return [
        rr.TimeColumn("frame", sequence=frames),
        rr.TimeColumn("time", duration=seconds),
    ]


def _transform_columns(transforms: np.ndarray):
    """``rr.Transform3D`` columns of (T, 4, 4) child-to-parent transforms."""
    import rerun as rr

    return rr.Transform3D.columns(
        translation=transforms[:, :3, 3].astype(np.float32),
        mat3x3=transforms[:, :3, :3].astype(np.float32),
    )


def _link_meshes(hand: RobotHand) -> dict[str, trimesh.Trimesh]:
    """The collision geometry of each link (link frame), shapes of one link merged."""
    by_link: dict[str, list[trimesh.Trimesh]] = {}
    for geom in hand.model.geometries:
        by_link.setdefault(geom.link, []).append(geom.mesh)
    return {
        link: meshes[0] if len(meshes) == 1 else trimesh.util.concatenate(meshes)
        for link, meshes in by_link.items()
    }


def _finger_links(hand: RobotHand, fingers: list[str]) -> dict[str, list[str]]:
    """Contact links of each finger named in the contact file that the hand has."""
    return {f: list(hand.spec.fingers[f].links) for f in fingers if f in hand.spec.fingers}


def write_recording(
    out: str | Path,
    sequence: Sequence,
    hand: RobotHand,
    q: np.ndarray,
    contact: np.ndarray | None = None,
    fingers: list[str] | None = None,
    *,
    object_mesh: trimesh.Trimesh | None = None,
    name: str | None = None,
    trajectory: str = "refine",
) -> Path:
    """Write one sequence with a robot-hand trajectory as a rerun recording, headless.

    Args:
        out: The ``.rrd`` file to write (``.rrd`` is appended if the name lacks it); written
            atomically, parent folders created.
        sequence: The aligned sequence: keypoints (T, 21, 3) and obj_pose (T, 4, 4), world frame.
        hand: The robot hand ``q`` is for.
        q: (T, dof) configurations in ``hand.joint_names`` order.
        contact: (T, F) bool contact state per finger, or None for no contact colours.
        fingers: (F,) finger names of the ``contact`` columns (thumb..little).
        object_mesh: The object mesh in its own frame; None logs the pose only.
        name: Recording name (default: ``sequence.obj_name``); also seeds the recording id.
        trajectory: Which trajectory ``q`` is (part of the recording id and name).

    Returns:
        The path written.

    Raises:
        ValueError: ``q``, ``contact`` or ``fingers`` do not match the sequence or each other.
    """
    import rerun as rr

    from dexflow.io.atomic import atomic_path

    out = Path(out)
    if out.suffix != ".rrd":
        out = out.with_name(out.name + ".rrd")
    num_frames = sequence.num_frames
    q = np.asarray(q, dtype=np.float64)
    if q.shape != (num_frames, hand.dof):
        raise ValueError(f"q: expected shape ({num_frames}, {hand.dof}), found {q.shape}")
    if contact is not None:
        contact = np.asarray(contact, dtype=bool)
        if fingers is None or contact.shape != (num_frames, len(fingers)):
            raise ValueError(
                f"contact: expected shape ({num_frames}, len(fingers)) with finger names, found "
                f"{contact.shape} and fingers={fingers}"
            )
    name = name or sequence.obj_name
    started = time.perf_counter()

    frames = np.arange(num_frames, dtype=np.int64)
    if sequence.timestamps is not None:
        seconds = np.asarray(sequence.timestamps, dtype=np.float64) - sequence.timestamps[0]
    else:
        seconds = frames / float(sequence.fps)
    index = _time_columns(frames, seconds)

    meshes = _link_meshes(hand)
    finger_links = _finger_links(hand, fingers) if contact is not None else {}
    contact_link_of = {link: f for f, links in finger_links.items() for link in links}
    links = list(meshes)
    links += [link for f in finger_links for link in finger_links[f] if link not in meshes]
    transforms = hand.link_transforms(q, links).detach().cpu().numpy()  # (T, L, 4, 4), one FK

    with atomic_path(out) as tmp:
        rec = rr.RecordingStream(
            _APPLICATION_ID, recording_id=recording_id(name, trajectory), send_properties=False
        )
        rec.save(tmp)
        rec.send_recording_name(f"{name} ({trajectory}, {hand.spec.name})")

        # Human keypoints and bones; an empty row where the hand was not tracked.
        valid = sequence.valid_mask
        keypoints = np.asarray(sequence.keypoints, dtype=np.float32)[valid]
        rec.log(
            "world/human/keypoints",
            rr.Points3D.from_fields(colors=_COLOR_KEYPOINTS, radii=_KEYPOINT_RADIUS_M),
            static=True,
        )
        rec.send_columns(
            "world/human/keypoints",
            indexes=index,
            columns=rr.Points3D.columns(positions=keypoints.reshape(-1, 3)).partition(
                valid.astype(np.int64) * NUM_KEYPOINTS
            ),
        )
        strips = keypoints[:, np.array(HAND_BONES)].reshape(-1, len(HAND_BONES[0]), 3)
        rec.log(
            "world/human/bones",
            rr.LineStrips3D.from_fields(colors=_COLOR_BONES, radii=_BONE_RADIUS_M),
            static=True,
        )
        rec.send_columns(
            "world/human/bones",
            indexes=index,
            columns=rr.LineStrips3D.columns(strips=strips).partition(
                valid.astype(np.int64) * len(HAND_BONES)
            ),
        )

        # Object: static mesh, pose per frame.
        if object_mesh is not None:
            rec.log("world/object", _mesh3d(object_mesh, _COLOR_OBJECT), static=True)
        rec.send_columns(
            "world/object",
            indexes=index,
            columns=_transform_columns(np.asarray(sequence.obj_pose, dtype=np.float64)),
        )

        # Robot links: static meshes (finger links without a static colour), world transforms.
        for i, link in enumerate(links):
            path = f"world/robot/{_entity(link)}"
            if link in meshes:
                color = None if link in contact_link_of else _COLOR_LINK
                rec.log(path, _mesh3d(meshes[link], color), static=True)
            rec.send_columns(path, indexes=index, columns=_transform_columns(transforms[:, i]))

        # Contact: finger link colours and one marker per finger.
        if finger_links:
            column = {f: fingers.index(f) for f in finger_links}
            colors = np.where(
                contact[..., None], np.array(_COLOR_CONTACT, _RGBA), np.array(_COLOR_FREE, _RGBA)
            ).astype(_RGBA)  # (T, F, 4)
            for link, finger in contact_link_of.items():
                if link in meshes:
                    rec.send_columns(
                        f"world/robot/{_entity(link)}",
                        indexes=index,
                        columns=rr.Mesh3D.columns(albedo_factor=colors[:, column[finger]]),
                    )
            order = list(finger_links)
            tip = [links.index(finger_links[f][-1]) for f in order]
            markers = transforms[:, tip, :3, 3].astype(np.float32)  # (T, F', 3)
            rec.log(
                "world/robot/contacts",
                rr.Points3D.from_fields(radii=_CONTACT_MARKER_RADIUS_M, labels=order),
                static=True,
            )
            rec.send_columns(
                "world/robot/contacts",
                indexes=index,
                columns=rr.Points3D.columns(
                    positions=markers.reshape(-1, 3),
                    colors=colors[:, [column[f] for f in order]].reshape(-1, 4),
                ).partition(np.full(num_frames, len(order))),
            )
        rec.flush()
        rec.disconnect()

    log.info(
        "wrote %s: %d frames, %d links, %.1f kB in %.2f s",
        out,
        num_frames,
        len(links),
        out.stat().st_size / 1e3,
        time.perf_counter() - started,
    )
    return out


def record_sequence(
    name_or_path: str | Path,
    out_path: str | Path | None = None,
    *,
    trajectory: str = "refine",
    project_root: str | Path | None = None,
    hand: RobotHand | None = None,
) -> Path:
    """Write the recording of one sequence of a project's pipeline outputs.

    Args:
        name_or_path: A sequence name (``025_mug__00_power``) or a sequence ``.npz`` path.
        out_path: The ``.rrd`` to write; default ``<project>/reports/rerun/<name>.rrd``
            (``<name>.<trajectory>.rrd`` for the other trajectories).
        trajectory: ``refine`` (data/refine), ``retarget`` (data/retarget/dexflow) or
            ``baseline`` (data/retarget/position).
        project_root: The project (holding ``params.yaml``, ``conf/`` and ``data/``); found from
            the working directory by default.
        hand: The robot hand; default the one ``params.yaml`` names.

    Returns:
        The path written.

    Raises:
        MissingInputError: the sequence or trajectory file is missing (names the file and the
            DVC stage that writes it). A missing contact file only logs a warning.
        ArtifactError: a trajectory or contact file has the wrong fields, shapes or joints.
    """
    from dexflow.objects.mesh import load_mesh

    root = Path(project_root) if project_root is not None else find_project_root()
    layout = Layout(root)
    inputs = resolve_inputs(name_or_path, trajectory, root)
    if hand is None:
        from dexflow.config import load_params
        from dexflow.hands.robot import cached_hand

        params = load_params(root / "params.yaml")
        hand = cached_hand(params.hand, layout.hand_dir)
    sequence = load_sequence(inputs.sequence, data_root=inputs.data_root)
    q = read_trajectory(inputs.trajectory, hand.joint_names, sequence.num_frames).q
    loaded = load_contact(inputs.contact, hand, sequence.num_frames)
    contact, fingers = (loaded.final, loaded.fingers) if loaded is not None else (None, None)
    default = inputs.name if trajectory == "refine" else f"{inputs.name}.{trajectory}"
    out = Path(out_path) if out_path is not None else layout.recording(default)
    return write_recording(
        out,
        sequence,
        hand,
        q,
        contact,
        fingers,
        object_mesh=load_mesh(inputs.data_root / sequence.obj_mesh),
        name=inputs.name,
        trajectory=trajectory,
    )


def open_viewer(path: str | Path) -> subprocess.Popen:
    """Start the rerun viewer on a recording, detached (``rerun <file>``)."""
    return subprocess.Popen(["rerun", str(path)])
