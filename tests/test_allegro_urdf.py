"""The bundled right Allegro Hand v4 URDF against an independent numpy forward kinematics.

The joint table below is copied from the public Allegro Hand v4 (right) dimensions, not read
from the URDF, so a typo in either shows up as a mismatch. Units: metres, radians.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pybullet as p
import pytest
import pytorch_kinematics as pk
import torch

import dexflow

URDF = Path(dexflow.__file__).parent / "hands" / "assets" / "allegro_right.urdf"

# name -> (parent, origin xyz, origin rpy, axis or None for fixed, (lower, upper) or None)
JOINTS: dict[str, tuple] = {
    "joint_0.0": (
        "base_link",
        (0, 0.0435, -0.001542),
        (-0.08726646255, 0, 0),
        (0, 0, 1),
        (-0.47, 0.47),
    ),
    "joint_1.0": ("link_0.0", (0, 0, 0.0164), (0, 0, 0), (0, 1, 0), (-0.196, 1.61)),
    "joint_2.0": ("link_1.0", (0, 0, 0.054), (0, 0, 0), (0, 1, 0), (-0.174, 1.709)),
    "joint_3.0": ("link_2.0", (0, 0, 0.0384), (0, 0, 0), (0, 1, 0), (-0.227, 1.618)),
    "joint_3.0_tip": ("link_3.0", (0, 0, 0.0387), (0, 0, 0), None, None),
    "joint_4.0": ("base_link", (0, 0, 0.0007), (0, 0, 0), (0, 0, 1), (-0.47, 0.47)),
    "joint_5.0": ("link_4.0", (0, 0, 0.0164), (0, 0, 0), (0, 1, 0), (-0.196, 1.61)),
    "joint_6.0": ("link_5.0", (0, 0, 0.054), (0, 0, 0), (0, 1, 0), (-0.174, 1.709)),
    "joint_7.0": ("link_6.0", (0, 0, 0.0384), (0, 0, 0), (0, 1, 0), (-0.227, 1.618)),
    "joint_7.0_tip": ("link_7.0", (0, 0, 0.0387), (0, 0, 0), None, None),
    "joint_8.0": (
        "base_link",
        (0, -0.0435, -0.001542),
        (0.08726646255, 0, 0),
        (0, 0, 1),
        (-0.47, 0.47),
    ),
    "joint_9.0": ("link_8.0", (0, 0, 0.0164), (0, 0, 0), (0, 1, 0), (-0.196, 1.61)),
    "joint_10.0": ("link_9.0", (0, 0, 0.054), (0, 0, 0), (0, 1, 0), (-0.174, 1.709)),
    "joint_11.0": ("link_10.0", (0, 0, 0.0384), (0, 0, 0), (0, 1, 0), (-0.227, 1.618)),
    "joint_11.0_tip": ("link_11.0", (0, 0, 0.0387), (0, 0, 0), None, None),
    "joint_12.0": (
        "base_link",
        (-0.0182, 0.019333, -0.045987),
        (0, -1.65806278845, -1.5707963259),
        (-1, 0, 0),
        (0.263, 1.396),
    ),
    "joint_13.0": ("link_12.0", (-0.027, 0.005, 0.0399), (0, 0, 0), (0, 0, 1), (-0.105, 1.163)),
    "joint_14.0": ("link_13.0", (0, 0, 0.0177), (0, 0, 0), (0, 1, 0), (-0.189, 1.644)),
    "joint_15.0": ("link_14.0", (0, 0, 0.0514), (0, 0, 0), (0, 1, 0), (-0.162, 1.719)),
    "joint_15.0_tip": ("link_15.0", (0, 0, 0.0543), (0, 0, 0), None, None),
    "palm_joint": ("base_link", (0, 0, -0.065), (0, 0, 0), None, None),
    "wrist_joint": ("palm", (0, 0, -0.03), (0, 0, 0), None, None),
}
REVOLUTE = [f"joint_{i}.0" for i in range(16)]
TIPS = ["link_3.0_tip", "link_7.0_tip", "link_11.0_tip", "link_15.0_tip"]
TOL = 1e-6


def _child_link(joint: str) -> str:
    if joint == "palm_joint":
        return "palm"
    if joint == "wrist_joint":
        return "wrist"
    return "link_" + joint.removeprefix("joint_")


def _rot_axis(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues: rotation by ``angle`` about the unit vector ``axis``."""
    k = np.asarray(axis, dtype=float)
    k = k / np.linalg.norm(k)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx


def _rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """URDF fixed-axis roll-pitch-yaw: Rz(yaw) @ Ry(pitch) @ Rx(roll)."""
    ex, ey, ez = np.eye(3)
    return _rot_axis(ez, yaw) @ _rot_axis(ey, pitch) @ _rot_axis(ex, roll)


def numpy_fk(q: dict[str, float]) -> dict[str, np.ndarray]:
    """World (base_link) 4x4 pose of every link; ``q`` maps revolute joint name -> angle."""
    poses = {"base_link": np.eye(4)}
    pending = dict(JOINTS)
    while pending:
        for name, (parent, xyz, rpy, axis, _) in list(pending.items()):
            if parent not in poses:
                continue
            local = np.eye(4)
            local[:3, :3] = _rpy(*rpy)
            local[:3, 3] = xyz
            motion = np.eye(4)
            if axis is not None:
                motion[:3, :3] = _rot_axis(np.array(axis), q[name])
            poses[_child_link(name)] = poses[parent] @ local @ motion
            del pending[name]
    return poses


def _random_configs(n: int, seed: int) -> list[dict[str, float]]:
    rng = np.random.default_rng(seed)
    lo = np.array([JOINTS[j][4][0] for j in REVOLUTE])
    hi = np.array([JOINTS[j][4][1] for j in REVOLUTE])
    return [dict(zip(REVOLUTE, rng.uniform(lo, hi), strict=True)) for _ in range(n)]


@pytest.fixture(scope="module")
def chain():
    return pk.build_chain_from_urdf(URDF.read_bytes()).to(dtype=torch.float64)


def _pk_tips(chain, q: dict[str, float]) -> dict[str, np.ndarray]:
    names = chain.get_joint_parameter_names()
    qt = torch.tensor([[q[n] for n in names]], dtype=torch.float64)
    frames = chain.forward_kinematics(qt)
    return {t: frames[t].get_matrix()[0, :3, 3].numpy() for t in TIPS}


def test_urdf_structure():
    root = ET.parse(URDF).getroot()
    assert root.get("name") == "allegro_right"
    links = {link.get("name") for link in root.findall("link")}
    assert links == {"base_link"} | {_child_link(j) for j in JOINTS}
    assert len(links) == 23
    joints = {j.get("name"): j for j in root.findall("joint")}
    assert set(joints) == set(JOINTS)
    for name, (parent, xyz, rpy, axis, limits) in JOINTS.items():
        j = joints[name]
        assert j.find("parent").get("link") == parent
        assert j.find("child").get("link") == _child_link(name)
        origin = j.find("origin")
        np.testing.assert_allclose([float(v) for v in origin.get("xyz").split()], xyz, atol=1e-12)
        np.testing.assert_allclose([float(v) for v in origin.get("rpy").split()], rpy, atol=1e-12)
        if axis is None:
            assert j.get("type") == "fixed"
            continue
        assert j.get("type") == "revolute"
        np.testing.assert_allclose([float(v) for v in j.find("axis").get("xyz").split()], axis)
        lim = j.find("limit")
        assert (float(lim.get("lower")), float(lim.get("upper"))) == limits
        assert float(lim.get("effort")) == 10.0
        assert float(lim.get("velocity")) == 3.14
    for link in root.findall("link"):
        assert float(link.find("inertial/mass").get("value")) > 0, link.get("name")
        assert link.get("name") in ("palm", "wrist") or link.findall("collision")
    for tip in TIPS:
        (col,) = root.find(f"link[@name='{tip}']").findall("collision")
        assert float(col.find("geometry/sphere").get("radius")) == 0.012
        assert col.find("origin").get("xyz") == "0 0 -0.012"


def test_hand_computed_tips_at_zero(chain):
    tips = _pk_tips(chain, dict.fromkeys(REVOLUTE, 0.0))
    # Index at q = 0: the finger is a straight chain along its own z of length
    # L = 0.0164 + 0.054 + 0.0384 + 0.0387 = 0.1475, rolled by -5 deg (-0.08726646255 rad)
    # about x, starting at (0, 0.0435, -0.001542). Rx(-5deg) (0, 0, L) = (0, L sin 5deg, L cos 5deg)
    # = (0, 0.01285547205, 0.14693871797), so the tip is at
    # (0, 0.05635547205, 0.14539671797); |tip| = 0.15593634864.
    np.testing.assert_allclose(tips["link_3.0_tip"], [0.0, 0.05635547205, 0.14539671797], atol=TOL)
    assert abs(np.linalg.norm(tips["link_3.0_tip"]) - 0.15593634864) < TOL
    # Middle at q = 0: straight up the z axis, 0.0007 + 0.1475 = 0.1482.
    np.testing.assert_allclose(tips["link_7.0_tip"], [0.0, 0.0, 0.1482], atol=TOL)
    # Ring mirrors index in y.
    np.testing.assert_allclose(
        tips["link_11.0_tip"], [0.0, -0.05635547205, 0.14539671797], atol=TOL
    )


@pytest.mark.parametrize("q", [dict.fromkeys(REVOLUTE, 0.0), *_random_configs(20, seed=0)])
def test_tips_match_numpy_fk(chain, q):
    assert sorted(chain.get_joint_parameter_names()) == sorted(REVOLUTE)
    expected = numpy_fk(q)
    got = _pk_tips(chain, q)
    for tip in TIPS:
        np.testing.assert_allclose(got[tip], expected[tip][:3, 3], atol=TOL, err_msg=tip)


def test_pybullet_limits_and_fk(chain):
    cid = p.connect(p.DIRECT)
    try:
        body = p.loadURDF(str(URDF), useFixedBase=True, physicsClientId=cid)
        info = [p.getJointInfo(body, i, physicsClientId=cid) for i in range(22)]
        assert p.getNumJoints(body, physicsClientId=cid) == 22
        index = {i[1].decode(): i[0] for i in info}
        link_index = {i[12].decode(): i[0] for i in info}
        revolute = [i for i in info if i[2] == p.JOINT_REVOLUTE]
        assert sorted(i[1].decode() for i in revolute) == sorted(REVOLUTE)
        for i in revolute:
            lo, hi = JOINTS[i[1].decode()][4]
            assert i[8] == pytest.approx(lo, abs=1e-12)
            assert i[9] == pytest.approx(hi, abs=1e-12)
            assert i[10] == pytest.approx(10.0) and i[11] == pytest.approx(3.14)
        for q in [dict.fromkeys(REVOLUTE, 0.0), *_random_configs(10, seed=1)]:
            for name, angle in q.items():
                p.resetJointState(body, index[name], angle, physicsClientId=cid)
            expected = _pk_tips(chain, q)
            for tip in TIPS:
                state = p.getLinkState(
                    body, link_index[tip], computeForwardKinematics=True, physicsClientId=cid
                )
                np.testing.assert_allclose(state[4], expected[tip], atol=TOL, err_msg=tip)
    finally:
        p.disconnect(cid)
