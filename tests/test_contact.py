"""Contact: hysteresis and frame-to-frame inference on hand-made states, distances on primitives."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from dexflow.hands import load_hand
from dexflow.objects.sdf import SignedDistanceGrid
from dexflow.params import ContactParams
from dexflow.stages.contact import finger_distances, hysteresis, infer_frames, state_changes

P = ContactParams()


def _col(values):
    return np.asarray(values, dtype=bool)[:, None]


def test_hysteresis_holds_between_the_thresholds():
    d_mm = np.array([20, 12, 9, 12, 15, 16, 12, 9.5, 14, 17])[:, None] / 1000
    state = hysteresis(d_mm, P.dis_min_m, P.dis_max_m)[:, 0]
    assert state.astype(int).tolist() == [0, 0, 1, 1, 1, 0, 0, 1, 1, 0]
    # Hovering around dis_min: a single threshold flickers, hysteresis does not.
    hover = np.array([20, 9, 11, 9, 11, 9, 12, 20])[:, None] / 1000
    single = hover < P.dis_min_m
    held = hysteresis(hover, P.dis_min_m, P.dis_max_m)
    assert state_changes(single)[0] == 6 and state_changes(held)[0] == 2


@pytest.mark.parametrize(
    ("before", "after"),
    [
        ([0, 0, 1, 0, 0], [0, 0, 0, 0, 0]),  # a one-frame spike is removed
        ([1, 1, 0, 1, 1], [1, 1, 1, 1, 1]),  # a one-frame gap is filled
        ([1, 1, 1, 0, 0, 0], [1, 1, 1, 0, 0, 0]),  # a real release is kept
        ([0, 1, 1, 1, 0], [0, 1, 1, 1, 0]),  # contacts are not shortened at their edges
        ([1, 0, 0, 1], [1, 0, 0, 1]),  # a two-frame gap is a real release
    ],
)
def test_frame_to_frame_inference(before, after):
    assert infer_frames(_col(before), 30.0, P)[:, 0].astype(int).tolist() == after


def test_inference_uses_the_sequences_frame_interval_and_the_guard():
    spike = _col([0, 0, 1, 0, 0])
    # At 0.5 fps, α v_f Δt = 0.96 > τ_c: the rule itself says "contact", so the spike stays.
    assert infer_frames(spike, 0.5, P)[2, 0]
    gap = _col([1, 1, 0, 1, 1])
    refused = np.zeros_like(gap)
    assert not infer_frames(gap, 30.0, P, allow_fill=refused)[2, 0]


def test_finger_distances_sign_on_a_box_with_a_hole():
    hand = load_hand("allegro")
    q = hand.zero()
    tip = hand.link_transforms(q, ["link_3.0_tip"])[0, 0, :3, 3].numpy()
    box = trimesh.creation.box(extents=(0.06, 0.06, 0.06))
    box = trimesh.Trimesh(
        box.vertices, box.faces[np.abs(box.face_normals[:, 2] + 1) > 1e-6]
    )  # open bottom
    assert not box.is_watertight
    sdf = SignedDistanceGrid.from_mesh(box, spacing=0.002)
    inside = np.eye(4)
    inside[:3, 3] = tip - [0.0, 0.0, 0.012]  # the box centred on the index fingertip sphere
    per_finger, dist, _ = finger_distances(hand, q.numpy(), inside[None], sdf)
    fingers = list(hand.spec.fingers)
    assert per_finger[0, fingers.index("index")] < -0.01  # deep inside: negative
    away = inside.copy()
    away[:3, 3] += [0.3, 0.0, 0.0]
    far, _, _ = finger_distances(hand, q.numpy(), away[None], sdf)
    assert (far > 0.1).all()
    # The per-finger value is the minimum over that finger's contact candidates only.
    links = np.asarray(hand.surface_point_links)
    idx = np.isin(links, hand.spec.fingers["ring"].links)
    assert per_finger[0, fingers.index("ring")] == pytest.approx(dist[0, idx].min())
    with torch.no_grad():
        assert len(hand.surface(q)[0][0]) == dist.shape[1]


def test_contact_sequence_writes_a_consistent_contact_map(tmp_path):
    """A hand touching a box: the map pairs contact-finger points with surface points."""
    from dexflow.stages.contact import _contact_map, contact_states

    hand = load_hand("allegro")
    q = hand.zero(4).numpy()
    tip = hand.link_transforms(hand.zero(), ["link_3.0_tip"])[0, 0, :3, 3].numpy()
    box = trimesh.creation.box(extents=(0.04, 0.04, 0.04))
    sdf = SignedDistanceGrid.from_mesh(box, spacing=0.002)
    pose = np.repeat(np.eye(4)[None], 4, axis=0)
    pose[:, :3, 3] = tip + np.array([0.0, 0.0, 0.024])  # the box face 4 mm beyond the index tip
    per_finger, dist, local = finger_distances(hand, q, pose, sdf)
    _, final = contact_states(per_finger, 30.0, P)
    index = list(hand.spec.fingers).index("index")
    assert final[:, index].all() and final.sum() == 4  # only the index finger, every frame
    points, face = trimesh.sample.sample_surface(box, 2000, seed=0)
    from scipy.spatial import cKDTree

    cmap = _contact_map(
        local,
        dist,
        final,
        list(hand.finger_point_masks.values()),
        cKDTree(points),
        box.face_normals[face],
        5,
    )
    assert set(cmap["map_finger"].tolist()) == {index} and len(cmap["map_frame"]) == 4 * 5
    assert np.abs(sdf.query(cmap["map_object_point"])).max() < 2e-3  # on the surface
    assert np.linalg.norm(cmap["map_hand_point"] - cmap["map_object_point"], axis=1).max() < 0.012
