"""``dexflow hand init``: fingers, keypoints, side, couplings and scale read from bare models.

The hands are built on the fly by :mod:`tests.hand_models` (right-hand canonical frame; left
versions reflected across the x-z plane there, independently of the x -> -x mirror that
``hand init`` writes).
"""

from __future__ import annotations

import re
import shutil
import textwrap
import xml.etree.ElementTree as ET
from dataclasses import replace

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from dexflow.errors import HandConfigError
from dexflow.hands import load_hand, load_hand_spec
from dexflow.hands.init import init_hand, mirror_model, propose_hand
from dexflow.hands.model import _origin, load_kinematic_model, resolve_model_path
from dexflow.hands.robot import RobotHand
from dexflow.human.model import forward_keypoints
from dexflow.io.sequence import Sequence
from dexflow.params import RetargetParams
from dexflow.stages.retarget import retarget_sequence
from dexflow.stages.scale_align import _mirror, scale_sequence
from dexflow.tools.cli import main as cli_main
from tests.hand_models import MIRROR, MJCF_HAND, gripper, hand4, hand5


def _inertia(inertial) -> np.ndarray:
    i = {k: float(v) for k, v in inertial.find("inertia").attrib.items()}
    return np.array(
        [
            [i["ixx"], i["ixy"], i["ixz"]],
            [i["ixy"], i["iyy"], i["iyz"]],
            [i["ixz"], i["iyz"], i["izz"]],
        ]
    )


def _keypoints(spec) -> dict[int, tuple[str, tuple[float, ...]]]:
    return {kp.mano: (kp.link, tuple(np.round(kp.offset, 4))) for kp in spec.keypoints}


def _joints(spec) -> dict[str, list[str]]:
    return {finger: fs.joints for finger, fs in spec.fingers.items()}


# ------------------------------------------------------------------------------- retarget


def _human_sequence(frames: int = 12, mirrored: bool = False) -> Sequence:
    """An average human right hand closing its fingers and thumb, turning a little."""
    t = np.linspace(0.0, 1.0, frames)[:, None]
    angles = np.zeros((frames, 20))
    angles[:, 4:] = 0.9 * t * np.tile([0.0, 1.0, 1.0, 0.8], 4)  # abduction, MCP, PIP, DIP
    angles[:, :4] = 0.6 * t * np.array([1.0, 0.5, 0.8, 0.8])
    wrist = np.repeat(np.eye(4)[None], frames, axis=0)
    wrist[:, :3, :3] = Rotation.from_rotvec(0.3 * t * np.array([[0.0, 0.0, 1.0]])).as_matrix()
    wrist[:, :3, 3] = [0.0, 0.0, 0.1]
    kp = forward_keypoints(angles, wrist)
    if mirrored:
        kp = kp @ MIRROR
    pose = np.repeat(np.eye(4)[None], frames, axis=0)
    return Sequence(keypoints=kp, obj_pose=pose, obj_mesh="m.obj", obj_name="m", fps=30.0)


def _retarget_error_mm(hand: RobotHand, seq: Sequence, search: str = "off") -> float:
    params = RetargetParams()
    params.global_search.mode = search
    scaled = scale_sequence(seq, hand.spec.scale, hand.spec.fingertip_offsets)
    return float(np.nanmean(retarget_sequence(scaled, hand, params).error_m) * 1000)


# ---------------------------------------------------------------------------------- tests


def test_allegro_urdf_reads_like_its_hand_written_yaml():
    path = resolve_model_path("pkg://dexflow/hands/assets/allegro_right.urdf")
    proposal = propose_hand(path)
    spec, written = proposal.spec, load_hand_spec("allegro")[0]
    assert proposal.detected_side == "right" and spec.side == "right" and not spec.mirrored
    assert _joints(spec) == _joints(written)  # thumb, index, middle, ring: every joint
    for finger in ("index", "middle", "ring"):
        assert spec.fingers[finger].links == written.fingers[finger].links
    generated = _keypoints(spec)
    for mano, (link, _) in _keypoints(written).items():
        if mano != 0:
            assert generated[mano][0] == link, mano
    # The thumb's base is its first joint; the wrist the far end of the palm boxes, where the
    # hand-written yaml puts the model's 'wrist' frame.
    assert generated[1][0] == "link_12.0"
    hand = RobotHand(spec, None)
    wrist_frame = hand.link_transforms(hand.zero(), ["wrist"])[0, 0, :3, 3].numpy()
    wrist = hand.keypoints(hand.zero())[0, hand.mano_indices.index(0)].numpy()
    np.testing.assert_allclose(wrist, wrist_frame, atol=1e-3)
    assert 1.2 < spec.scale < 1.7 and not proposal.guesses and not spec.couplings


def test_shadow_mjcf_reads_like_its_hand_written_yaml():
    proposal = propose_hand(
        resolve_model_path("pkg://gymnasium_robotics/envs/assets/hand/reach.xml")
    )
    spec, written = proposal.spec, load_hand_spec("shadow")[0]
    assert spec.root == written.root == "robot0:forearm" and spec.side == "right"
    assert _joints(spec) == _joints(written)
    assert spec.extra_joints == written.extra_joints  # the wrist
    assert spec.surface_exclude == written.surface_exclude
    assert [(c.joint, c.leader) for c in spec.couplings] == [
        (c.joint, c.leader) for c in written.couplings
    ]  # the tendons tying J0 to J1
    for ours, theirs in zip(spec.couplings, written.couplings, strict=True):
        assert ours.ratio == pytest.approx(theirs.ratio, rel=1e-9) and ours.offset == 0.0
    for finger in ("index", "middle", "ring", "little"):
        assert spec.fingers[finger].links == written.fingers[finger].links
    assert set(written.fingers["thumb"].links) <= set(spec.fingers["thumb"].links)
    generated = _keypoints(spec)
    for mano in (4, 8, 12, 16, 20, 2, 6, 10, 14):  # tips and middles, as written by hand
        assert generated[mano][0] == _keypoints(written)[mano][0]
    assert generated[9][0] == "robot0:mfproximal"  # at the knuckle (mfknuckle in the yaml)
    assert generated[17][0] == "robot0:lfproximal"  # past the little finger's metacarpal
    assert proposal.fingers[-1].unmapped == ["robot0:lfmetacarpal"]
    assert spec.scale == pytest.approx(written.scale, rel=0.02)
    assert proposal.opposition["thumb"] > 2 * max(
        v for k, v in proposal.opposition.items() if k != "thumb"
    )


def test_four_finger_hand_without_little_finger(tmp_path):
    proposal = propose_hand(hand4(tmp_path))
    spec = proposal.spec
    assert _joints(spec) == {
        "thumb": ["th_abd", "th_mcp", "th_pip", "th_dip"],
        "index": ["if_abd", "if_mcp", "if_pip", "if_dip"],
        "middle": ["mf_abd", "mf_mcp", "mf_pip", "mf_dip"],
        "ring": ["rf_abd", "rf_mcp", "rf_pip", "rf_dip"],
    }
    # Abduction and flexion at one point are one keypoint (the flexing link); no tip frames,
    # so tips are the far ends of the distal boxes.
    assert _keypoints(spec) == {
        0: ("palm", (0.0, 0.0, 0.0)),
        1: ("th_proximal", (0, 0, 0)),
        2: ("th_middle", (0, 0, 0)),
        4: ("th_distal", (0.0, 0.0, 0.03)),
        5: ("if_proximal", (0, 0, 0)),
        6: ("if_middle", (0, 0, 0)),
        8: ("if_distal", (0.0, 0.0, 0.024)),
        9: ("mf_proximal", (0, 0, 0)),
        10: ("mf_middle", (0, 0, 0)),
        12: ("mf_distal", (0.0, 0.0, 0.025)),
        13: ("rf_proximal", (0, 0, 0)),
        14: ("rf_middle", (0, 0, 0)),
        16: ("rf_distal", (0.0, 0.0, 0.024)),
    }
    assert spec.fingers["index"].links == ["if_proximal", "if_middle", "if_distal"]
    assert proposal.detected_side == "right" and not proposal.guesses
    assert spec.extra_joints == [] and spec.couplings == [] and spec.surface_exclude == []
    assert 0.9 < spec.scale < 1.15  # a human-sized hand


def test_three_finger_gripper_finds_the_opposing_thumb_and_says_what_it_guessed(tmp_path):
    out = tmp_path / "gripper.yaml"
    proposal = init_hand(gripper(tmp_path), out)
    spec = proposal.spec
    # The thumb opposes the others; they sit symmetrically, so the index is where a right
    # hand's would be (+y, the side of the thumb in the human canonical frame).
    assert _joints(spec) == {
        "thumb": ["t_mcp", "t_pip"],
        "index": ["a_mcp", "a_pip"],
        "middle": ["b_mcp", "b_pip"],
    }
    # Two joints per chain are not a human finger's three: only the tips are mapped.
    assert _keypoints(spec) == {
        0: ("palm", (0, 0, 0)),
        4: ("t_tip", (0, 0, 0)),
        8: ("a_tip", (0, 0, 0)),
        12: ("b_tip", (0, 0, 0)),
    }
    assert proposal.fingers[0].unmapped == ["t_proximal", "t_middle"]
    guessed = " ".join(text for _, text in proposal.guesses)
    assert "midway across the palm" in guessed and "mirror-symmetric" in guessed
    assert "only its tip is mapped" in guessed
    text = out.read_text()
    assert text.count("# GUESS") == len(proposal.guesses)
    assert load_hand(out).spec.fingers == spec.fingers  # the yaml reads back as proposed


def test_mimic_joints_wrist_and_little_finger(tmp_path):
    proposal = propose_hand(hand5(tmp_path))
    spec = proposal.spec
    assert list(spec.fingers) == ["thumb", "index", "middle", "ring", "little"]
    assert [spec.fingers[f].joints[0] for f in spec.fingers] == [
        "th_abd", "if_abd", "mf_abd", "rf_abd", "lf_abd"
    ]  # fmt: skip
    assert spec.extra_joints == ["wrist"] and spec.surface_exclude == ["forearm"]
    assert [(c.joint, c.leader, c.ratio, c.offset) for c in spec.couplings] == [
        (f"{p}_dip", f"{p}_pip", 0.7, 0.0) for p in ("if", "mf", "rf", "lf")
    ]
    kp = _keypoints(spec)
    assert [kp[k][0] for k in (4, 8, 12, 16, 20)] == [
        "th_tip",
        "if_tip",
        "mf_tip",
        "rf_tip",
        "lf_tip",
    ]
    assert [kp[k][0] for k in (17, 18)] == ["lf_proximal", "lf_middle"]
    assert kp[0] == ("palm", (0.0, 0.0, 0.0))
    hand = RobotHand(spec, None)
    q = hand.apply_couplings(hand.clamp(torch.full((1, hand.dof), 0.5, dtype=torch.float64)))
    dip, pip = hand.joint_names.index("if_dip"), hand.joint_names.index("if_pip")
    assert float(q[0, dip]) == pytest.approx(0.7 * float(q[0, pip]))


@pytest.mark.parametrize("build", [hand4, hand5])
def test_side_is_read_from_the_geometry(tmp_path, build):
    right, left = propose_hand(build(tmp_path, "right")), propose_hand(build(tmp_path, "left"))
    assert (right.detected_side, left.detected_side) == ("right", "left")
    assert (right.spec.side, left.spec.side) == ("right", "left")
    assert _joints(right.spec) == _joints(left.spec)
    assert {k: v[0] for k, v in _keypoints(right.spec).items()} == {
        k: v[0] for k, v in _keypoints(left.spec).items()
    }
    stated = propose_hand(build(tmp_path, "left"), side="right")
    assert stated.spec.side == "right"
    assert any(
        "geometry shows a left hand" in text for key, text in stated.guesses if key == "side"
    )


def test_left_hand_is_used_as_it_is_and_right_sequences_are_mirrored_to_it(tmp_path):
    right = init_hand(hand4(tmp_path, "right"), tmp_path / "r.yaml").spec
    left = init_hand(hand4(tmp_path, "left"), tmp_path / "l.yaml").spec
    assert (left.side, left.mirrored, left.model) == ("left", False, "hand4_left.urdf")
    assert "side: left" in (tmp_path / "l.yaml").read_text()
    # scale_align mirrors a human hand of the other side than the robot's, with its scene.
    seq = _human_sequence()
    assert _mirror(seq, left) and not _mirror(seq, right)
    assert not _mirror(replace(seq, side="left"), left)
    on_right = _retarget_error_mm(load_hand(tmp_path / "r.yaml"), seq)
    on_left = _retarget_error_mm(load_hand(tmp_path / "l.yaml"), _human_sequence(mirrored=True))
    assert on_left == pytest.approx(on_right, rel=0.02, abs=0.05), (on_left, on_right)
    unmirrored = _retarget_error_mm(load_hand(tmp_path / "l.yaml"), seq)
    assert unmirrored > 2 * on_right  # a right human hand does not fit the left robot hand


def test_left_hand_mirrored_on_request_retargets_as_the_right_one(tmp_path):
    right = init_hand(hand5(tmp_path, "right"), tmp_path / "right.yaml").spec
    left = init_hand(hand5(tmp_path, "left"), tmp_path / "left.yaml", mirror=True).spec
    assert (left.side, left.mirrored, left.model) == ("left", True, "left_mirrored.urdf")
    assert "mirrored: true" in (tmp_path / "left.yaml").read_text()
    assert not _mirror(_human_sequence(), left)  # the mirror image is a right hand
    assert _joints(left) == _joints(right) and left.couplings == right.couplings
    np.testing.assert_allclose(
        [kp.offset for kp in left.keypoints], [kp.offset for kp in right.keypoints], atol=1e-6
    )
    seq = _human_sequence()
    hands = [load_hand(tmp_path / f"{side}.yaml") for side in ("right", "left")]
    errors = [_retarget_error_mm(hand, seq) for hand in hands]
    assert errors[1] == pytest.approx(errors[0], rel=1e-3, abs=1e-3), errors
    # The mirror keeps the masses: the simulator sees the same hand.
    masses = [
        sorted(float(v) for v in re.findall(r'<mass value="([^"]+)"', path.read_text()))
        for path in (tmp_path / "hand5_left.urdf", tmp_path / "left_mirrored.urdf")
    ]
    assert masses[0] == pytest.approx(masses[1])


@pytest.mark.parametrize("which", ["allegro", "hand5", "mjcf"])
def test_mirrored_model_is_the_reflection(tmp_path, which):
    if which == "allegro":
        path = resolve_model_path("pkg://dexflow/hands/assets/allegro_right.urdf")
        model = load_kinematic_model(path)
    elif which == "hand5":
        model = load_kinematic_model(hand5(tmp_path, "left"))
    else:
        (tmp_path / "mj.xml").write_text(MJCF_HAND)
        model = load_kinematic_model(tmp_path / "mj.xml", "mount")
    mirrored = load_kinematic_model(mirror_model(model, tmp_path / "mirrored.urdf"))
    assert mirrored.joint_names == model.joint_names
    np.testing.assert_allclose(mirrored.lower, model.lower)
    np.testing.assert_allclose(mirrored.upper, model.upper)
    q = np.random.default_rng(0).uniform(model.lower, model.upper, size=(5, len(model.lower)))
    fk = [
        m.chain.to(dtype=torch.float64).forward_kinematics(torch.as_tensor(q))
        for m in (model, mirrored)
    ]
    m4 = np.diag([-1.0, 1.0, 1.0, 1.0])
    root = fk[0][model.root].get_matrix().numpy()
    for frame in model.frames:
        expected = m4 @ np.linalg.inv(root) @ fk[0][frame].get_matrix().numpy() @ m4
        np.testing.assert_allclose(fk[1][frame].get_matrix().numpy(), expected, atol=1e-6)
    # Inertials too: the centre of mass and the inertia tensor in the link frame, reflected.
    if model.format == "urdf":
        ours, theirs = (
            {link.get("name"): link.find("inertial") for link in ET.parse(p).getroot().iter("link")}
            for p in (model.path, tmp_path / "mirrored.urdf")
        )
        for name, inertial in ours.items():
            if inertial is None:
                continue
            pose, pose_m = _origin(inertial), _origin(theirs[name])
            tensor, tensor_m = (_inertia(x) for x in (inertial, theirs[name]))
            np.testing.assert_allclose(pose_m[:3, 3], MIRROR @ pose[:3, 3], atol=1e-9)
            np.testing.assert_allclose(
                pose_m[:3, :3] @ tensor_m @ pose_m[:3, :3].T,
                MIRROR @ pose[:3, :3] @ tensor @ pose[:3, :3].T @ MIRROR,
                atol=1e-12,
            )
    # Collision shapes are reflected too: the surface points of the mirror are the reflection.
    for ours, theirs in zip(model.geometries, mirrored.geometries, strict=True):
        assert ours.link == theirs.link
        np.testing.assert_allclose(
            np.sort(theirs.mesh.bounds[:, 0]), np.sort(-ours.mesh.bounds[:, 0]), atol=1e-7
        )


def test_mjcf_root_and_couplings_from_equalities_and_tendons(tmp_path):
    (tmp_path / "mj.xml").write_text(MJCF_HAND)
    proposal = propose_hand(tmp_path / "mj.xml")
    spec = proposal.spec
    assert spec.root == "mount" and spec.extra_joints == ["wrist"]  # not the free object
    assert spec.fingers["thumb"].joints == ["t1", "t2"]
    coupled = {c.joint: (c.leader, round(c.ratio, 9), round(c.offset, 9)) for c in spec.couplings}
    # a2 = 0.1 + 0.8 a1 (joint equality); 0.01 b1 - 0.008 b2 = 0 (tight tendon); the loose
    # tendon on the thumb ties nothing.
    assert coupled == {"a2": ("a1", 0.8, 0.1), "b2": ("b1", 1.25, 0.0)}
    # A mirror-symmetric gripper: the index is where a right hand's would be; a tip site.
    assert (spec.fingers["index"].joints, _keypoints(spec)[8][0]) == (["a1", "a2"], "a_tip")
    # A left MJCF hand is written as a mirrored URDF and keeps its couplings.
    left = init_hand(tmp_path / "mj.xml", tmp_path / "mjleft.yaml", side="left", mirror=True)
    assert left.spec.mirrored and left.spec.root == "" and left.spec.couplings == spec.couplings
    assert load_hand(tmp_path / "mjleft.yaml").model.format == "urdf"


def test_generated_configs_retarget_like_hand_written_ones(tmp_path):
    """Keypoint error of the generated yaml within 1.5x that of one written by hand."""
    written = {
        "hand4": """\
            name: hand4
            model: hand4_right.urdf
            keypoints:
              - {link: th_distal, mano: 4, offset: [0, 0, 0.03]}
              - {link: if_distal, mano: 8, offset: [0, 0, 0.024]}
              - {link: mf_distal, mano: 12, offset: [0, 0, 0.025]}
              - {link: rf_distal, mano: 16, offset: [0, 0, 0.024]}
              - {link: th_middle, mano: 2}
              - {link: if_middle, mano: 6}
              - {link: mf_middle, mano: 10}
              - {link: rf_middle, mano: 14}
              - {link: mf_proximal, mano: 9}
              - {link: rf_proximal, mano: 13}
              - {link: palm, mano: 0}
            fingers:
              thumb: {joints: [th_abd, th_mcp, th_pip, th_dip], links: [th_middle, th_distal]}
              index: {joints: [if_abd, if_mcp, if_pip, if_dip], links: [if_middle, if_distal]}
              middle: {joints: [mf_abd, mf_mcp, mf_pip, mf_dip], links: [mf_middle, mf_distal]}
              ring: {joints: [rf_abd, rf_mcp, rf_pip, rf_dip], links: [rf_middle, rf_distal]}
            surface_points: 500
            """,
        "gripper": """\
            name: gripper
            model: gripper.urdf
            keypoints:
              - {link: t_tip, mano: 4}
              - {link: a_tip, mano: 8}
              - {link: b_tip, mano: 12}
              - {link: palm, mano: 0}
            fingers:
              thumb: {joints: [t_mcp, t_pip], links: [t_proximal, t_middle]}
              index: {joints: [a_mcp, a_pip], links: [a_proximal, a_middle]}
              middle: {joints: [b_mcp, b_pip], links: [b_proximal, b_middle]}
            surface_points: 500
            """,
    }
    models = {"hand4": hand4(tmp_path), "gripper": gripper(tmp_path)}
    seq = _human_sequence()
    for name, text in written.items():
        (tmp_path / f"{name}_written.yaml").write_text(textwrap.dedent(text))
        init_hand(models[name], tmp_path / f"{name}_generated.yaml")
        errors = [
            _retarget_error_mm(load_hand(tmp_path / f"{name}_{kind}.yaml"), seq)
            for kind in ("written", "generated")
        ]
        assert errors[1] <= 1.5 * errors[0], (name, errors)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["allegro", "shadow"])
def test_builtin_hands_retarget_a_demo_sequence_within_1_5x(tmp_path, name):
    from dexflow.data.demo import generate_demo
    from dexflow.io.layout import StageDir
    from dexflow.io.sequence import load_sequence
    from dexflow.params import DemoConfig

    cfg = DemoConfig(
        seed=1, objects=["025_mug"], sequences_per_object=1, min_frames=40, max_frames=45
    )
    generate_demo(cfg, tmp_path / "demo")
    seq = load_sequence(StageDir(tmp_path / "demo").sequence_files()[0])
    model = {
        "allegro": "pkg://dexflow/hands/assets/allegro_right.urdf",
        "shadow": "pkg://gymnasium_robotics/envs/assets/hand/reach.xml",
    }[name]
    init_hand(model, tmp_path / f"{name}_init.yaml")
    errors = {
        kind: _retarget_error_mm(load_hand(hand), seq, search="first_frame")
        for kind, hand in (("written", name), ("generated", tmp_path / f"{name}_init.yaml"))
    }
    assert errors["generated"] <= 1.5 * errors["written"], errors


def test_cli_writes_a_checked_yaml_and_prints_its_guesses(tmp_path, capsys, monkeypatch):
    model = gripper(tmp_path)
    monkeypatch.chdir(tmp_path)
    assert cli_main(["hand", "init", str(model)]) == 0  # no conf/hand here: ./gripper.yaml
    out = capsys.readouterr().out
    assert "thumb  2 joints from 't_proximal'" in out and "GUESS (fingers)" in out
    assert "`dexflow hand check gripper.yaml` passes" in out
    assert load_hand_spec(tmp_path / "gripper.yaml")[0].model == "gripper.urdf"
    assert cli_main(["hand", "check", "gripper.yaml", "--png", "g.png"]) == 0
    assert cli_main(["hand", "init", str(model)]) == 2  # exists: not replaced without --force
    assert "--force" in capsys.readouterr().err
    assert cli_main(["hand", "init", str(model), "--side", "left", "--mirror", "-o", "l.yaml"]) == 0
    assert load_hand_spec(tmp_path / "l.yaml")[0].mirrored


def test_side_and_mirrored_are_validated_and_default_to_a_right_hand(tmp_path):
    spec, _ = load_hand_spec("allegro")
    assert (spec.side, spec.mirrored) == ("right", False)
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: bad\nmodel: x.urdf\nside: up\n")
    with pytest.raises(HandConfigError, match="side must be 'right' or 'left', found 'up'"):
        load_hand_spec(bad)
    bad.write_text("name: bad\nmodel: x.urdf\nmirrored: maybe\n")
    with pytest.raises(HandConfigError, match="mirrored"):
        load_hand_spec(bad)
    with pytest.raises(HandConfigError, match="side must be"):
        propose_hand(gripper(tmp_path), side="both")


def test_a_generated_yaml_composes_into_the_pipeline_params(tmp_path):
    """In conf/hand/ the yaml is a hand option: ``hand=<name>`` composes and validates, and the
    model resolves against conf/hand/ as the stages resolve it."""
    from dexflow.config import compose_params, load_params
    from dexflow.io.layout import project_root

    conf = tmp_path / "conf"
    shutil.copytree(project_root() / "conf", conf)
    model = hand4(conf / "hand", "left")
    init_hand(model, conf / "hand" / "myhand.yaml")
    params = load_params(compose_params(["hand=myhand"], tmp_path / "p.yaml", config_dir=conf))
    assert (params.hand.name, params.hand.side, params.hand.mirrored) == ("myhand", "left", False)
    assert params.hand.model == "hand4_left.urdf"
    hand = RobotHand(params.hand, conf / "hand")
    assert list(hand.fingers) == ["thumb", "index", "middle", "ring"]
