"""Robot hands: FK against MuJoCo, batching, gradients, export to pybullet, configs, hand check."""

from __future__ import annotations

import itertools
import textwrap
import xml.etree.ElementTree as ET

import mujoco
import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial.transform import Rotation

from dexflow.errors import HandConfigError
from dexflow.hands import load_hand
from dexflow.hands.check import check_hand
from dexflow.hands.export import export_urdf
from dexflow.hands.model import _origin
from dexflow.hands.robot import base_transform, sharp_edge_points
from dexflow.tools.cli import main as cli_main


@pytest.fixture(scope="module")
def shadow():
    return load_hand("shadow")


@pytest.fixture(scope="module")
def allegro():
    return load_hand("allegro")


def _random_q(hand, n, seed=0, base=False):
    rng = np.random.default_rng(seed)
    lo, hi = hand.lower.numpy().copy(), hand.upper.numpy().copy()
    q = rng.uniform(lo, hi, size=(n, hand.dof))
    q[:, :6] = rng.uniform(-0.5, 0.5, size=(n, 6)) if base else 0.0
    return torch.as_tensor(q)


def test_shadow_fk_matches_mujoco(shadow):
    m = shadow.model.mj_model
    d = mujoco.MjData(m)
    frames = [f for f in shadow.model.frames if f != shadow.model.root]
    bodies = {m.body(i).name: i for i in range(m.nbody)}
    sites = {m.site(i).name: i for i in range(m.nsite)}
    mount = m.body(bodies[shadow.model.root]).parentid[0]
    assert len(shadow.hand_joint_names) == 24
    for q in _random_q(shadow, 8, seed=1):
        for j, name in enumerate(shadow.hand_joint_names):
            d.qpos[m.joint(name).qposadr[0]] = float(q[6 + j])
        mujoco.mj_kinematics(m, d)
        rot_mount, pos_mount = d.xmat[mount].reshape(3, 3), d.xpos[mount]
        ours = shadow.link_transforms(q, frames)[0].numpy()
        for i, name in enumerate(frames):
            world = d.xpos[bodies[name]] if name in bodies else d.site_xpos[sites[name]]
            expected = rot_mount.T @ (world - pos_mount)
            np.testing.assert_allclose(ours[i, :3, 3], expected, atol=1e-6, err_msg=name)


def test_shadow_couplings_are_the_mjcf_tendons(shadow):
    m = shadow.model.mj_model
    for coupling in shadow.spec.couplings:
        finger = coupling.joint.split(":")[1][:2]
        t = m.tendon(f"robot0:T_{finger}J1c")
        adr, num = int(m.tendon_adr[t.id]), int(m.tendon_num[t.id])
        coef = {m.joint(int(m.wrap_objid[adr + k])).name: m.wrap_prm[adr + k] for k in range(num)}
        assert coupling.ratio == pytest.approx(
            -coef[coupling.leader] / coef[coupling.joint], rel=1e-9
        )
    q = shadow.apply_couplings(_random_q(shadow, 3))
    ffj0, ffj1 = shadow.joint_names.index("robot0:FFJ0"), shadow.joint_names.index("robot0:FFJ1")
    torch.testing.assert_close(q[:, ffj0], q[:, ffj1] * shadow.spec.couplings[0].ratio)


@pytest.mark.parametrize("name", ["shadow", "allegro"])
def test_batch_equals_one_at_a_time_and_float32_agrees(name, shadow, allegro):
    hand = {"shadow": shadow, "allegro": allegro}[name]
    q = _random_q(hand, 6, seed=2, base=True)
    batch = hand.keypoints(q)
    for i in range(len(q)):
        torch.testing.assert_close(batch[i], hand.keypoints(q[i])[0], atol=1e-12, rtol=0)
    points, normals = hand.surface(q)
    torch.testing.assert_close(points[3], hand.surface(q[3])[0][0], atol=1e-12, rtol=0)
    assert points.shape == normals.shape and points.shape[1] >= 1800
    single = load_hand(name, dtype=torch.float32)
    torch.testing.assert_close(single.keypoints(q.float()), batch.float(), atol=1e-5, rtol=0)


@pytest.mark.parametrize("name", ["shadow", "allegro"])
def test_gradients_flow_and_match_finite_differences(name, shadow, allegro):
    hand = {"shadow": shadow, "allegro": allegro}[name]
    q = _random_q(hand, 1, seed=3, base=True)[0]
    jac = torch.autograd.functional.jacobian(lambda x: hand.keypoints(x)[0].reshape(-1), q)
    eps = 1e-6
    for j in range(hand.dof):
        dq = torch.zeros_like(q)
        dq[j] = eps
        fd = (hand.keypoints(q + dq)[0] - hand.keypoints(q - dq)[0]).reshape(-1) / (2 * eps)
        torch.testing.assert_close(jac[:, j], fd, atol=1e-6, rtol=1e-5)
    assert jac[:, 6:].abs().sum() > 0


def test_floating_base_moves_everything_rigidly(allegro):
    q = _random_q(allegro, 1, seed=4)
    moved = q.clone()
    moved[0, :3] = torch.tensor([0.1, -0.2, 0.3])
    moved[0, 5] = np.pi / 2  # about z
    rz = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    expected = allegro.keypoints(q)[0] @ rz.T + moved[0, :3]
    torch.testing.assert_close(allegro.keypoints(moved)[0], expected, atol=1e-12, rtol=0)


def test_floating_base_rotation_is_rx_ry_rz_and_differentiable():
    q_base = torch.as_tensor(np.random.default_rng(5).uniform(-3, 3, size=(8, 6)))
    t = base_transform(q_base).numpy()
    for (x, y, z, a, b, c), pose in zip(q_base.numpy(), t, strict=True):
        rot = Rotation.from_rotvec([a, 0, 0]) * Rotation.from_rotvec([0, b, 0])
        rot = rot * Rotation.from_rotvec([0, 0, c])  # Rx Ry Rz: each about the rotated axes
        np.testing.assert_allclose(pose[:3, :3], rot.as_matrix(), atol=1e-12)
        np.testing.assert_allclose(pose[:3, 3], [x, y, z], atol=0)
        np.testing.assert_allclose(pose[3], [0, 0, 0, 1], atol=0)
    assert torch.autograd.gradcheck(base_transform, (q_base[:2].clone().requires_grad_(),))


def test_mjcf_geometry_poses_match_mujoco(shadow):
    """Every collision shape sits in its body where MuJoCo puts it (quaternions are w, x, y, z)."""
    m = shadow.model.mj_model
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    rotated = 0
    for geom in shadow.model.geometries:
        body = m.body(geom.link).id
        rot_body = d.xmat[body].reshape(3, 3)
        in_body = []
        for g in np.flatnonzero(m.geom_bodyid == body):
            pose = np.eye(4)
            pose[:3, :3] = rot_body.T @ d.geom_xmat[g].reshape(3, 3)
            pose[:3, 3] = rot_body.T @ (d.geom_xpos[g] - d.xpos[body])
            in_body.append(pose)
        assert min(np.abs(geom.transform - ref).max() for ref in in_body) < 1e-9, geom.link
        rotated += not np.allclose(geom.transform[:3, :3], np.eye(3), atol=1e-6)
    assert rotated > 0  # the check sees the quaternion convention


def test_urdf_origin_rpy_is_about_the_fixed_axes():
    element = ET.fromstring(
        '<collision><origin xyz="0.1 -0.2 0.3" rpy="0.3 -0.5 1.1"/></collision>'
    )
    yaw, pitch, roll = (Rotation.from_rotvec(v) for v in ([0, 0, 1.1], [0, -0.5, 0], [0.3, 0, 0]))
    pose = _origin(element)
    np.testing.assert_allclose(pose[:3, :3], (yaw * pitch * roll).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(pose[:3, 3], [0.1, -0.2, 0.3], atol=0)
    np.testing.assert_allclose(pose[3], [0, 0, 0, 1], atol=0)
    np.testing.assert_allclose(_origin(ET.fromstring("<collision/>")), np.eye(4), atol=0)


def test_surface_normals_point_outwards(allegro):
    points, normals = allegro.surface(allegro.zero())
    p, n = points[0].numpy(), normals[0].numpy()
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-9)
    links = np.asarray(allegro.surface_point_links)
    t = dict(
        zip(
            allegro.surface_links,
            allegro.link_transforms(allegro.zero(), allegro.surface_links)[0].numpy(),
            strict=True,
        )
    )
    outward = []
    for link in allegro.surface_links:
        own = [
            g.mesh.copy().apply_transform(t[link])
            for g in allegro.model.geometries
            if g.link == link
        ]
        sel = links == link
        out_step = np.any([m.contains(p[sel] + 1e-3 * n[sel]) for m in own], axis=0)
        in_step = np.any([m.contains(p[sel] - 1e-3 * n[sel]) for m in own], axis=0)
        outward.append(~out_step & in_step)
    # Every point leaves its own link's shapes along its normal (a few sit where two overlap).
    assert np.concatenate(outward).mean() > 0.95


def test_mjcf_export_loads_in_pybullet_with_matching_link_frames(shadow, tmp_path):
    import pybullet as p

    path = export_urdf(shadow.model, tmp_path / "shadow.urdf")
    client = p.connect(p.DIRECT)
    try:
        body = p.loadURDF(str(path), useFixedBase=True, physicsClientId=client)
        info = [
            p.getJointInfo(body, i, physicsClientId=client)
            for i in range(p.getNumJoints(body, physicsClientId=client))
        ]
        joints = {i[1].decode(): i[0] for i in info}
        links = {i[12].decode(): i[0] for i in info}
        revolute = [i[1].decode() for i in info if i[2] == p.JOINT_REVOLUTE]
        assert sorted(revolute) == sorted(shadow.hand_joint_names)
        frames = [f for f in shadow.model.frames if f in links]
        for q in _random_q(shadow, 5, seed=5):
            for j, name in enumerate(shadow.hand_joint_names):
                p.resetJointState(body, joints[name], float(q[6 + j]), physicsClientId=client)
            ours = shadow.link_transforms(q, frames)[0].numpy()
            for i, name in enumerate(frames):
                state = p.getLinkState(
                    body, links[name], computeForwardKinematics=True, physicsClientId=client
                )
                np.testing.assert_allclose(state[4], ours[i, :3, 3], atol=1e-6, err_msg=name)
    finally:
        p.disconnect(client)


GRIPPER_URDF = """<?xml version="1.0"?>
<robot name="gripper3">
  <link name="base"><inertial><mass value="0.2"/><inertia ixx="1e-4" iyy="1e-4" izz="1e-4" ixy="0" ixz="0" iyz="0"/></inertial><collision><geometry><box size="0.06 0.06 0.02"/></geometry></collision></link>
  {fingers}
</robot>"""

FINGER = """
  <link name="f{i}_prox"><inertial><mass value="0.02"/><inertia ixx="3e-6" iyy="3e-6" izz="3e-6" ixy="0" ixz="0" iyz="0"/></inertial><collision><origin xyz="0 0 0.02"/><geometry><box size="0.012 0.012 0.04"/></geometry></collision></link>
  <link name="f{i}_dist"><inertial><mass value="0.01"/><inertia ixx="1e-6" iyy="1e-6" izz="1e-6" ixy="0" ixz="0" iyz="0"/></inertial><collision><origin xyz="0 0 0.015"/><geometry><box size="0.01 0.01 0.03"/></geometry></collision></link>
  <link name="f{i}_tip"><inertial><mass value="0.001"/><inertia ixx="1e-8" iyy="1e-8" izz="1e-8" ixy="0" ixz="0" iyz="0"/></inertial></link>
  <joint name="f{i}_j0" type="revolute"><parent link="base"/><child link="f{i}_prox"/>
    <origin xyz="{x} {y} 0.01" rpy="0 0 {yaw}"/><axis xyz="1 0 0"/><limit lower="-0.5" upper="1.2" effort="1" velocity="1"/></joint>
  <joint name="f{i}_j1" type="revolute"><parent link="f{i}_prox"/><child link="f{i}_dist"/>
    <origin xyz="0 0 0.04"/><axis xyz="1 0 0"/><limit lower="0" upper="1.5" effort="1" velocity="1"/></joint>
  <joint name="f{i}_tipj" type="fixed"><parent link="f{i}_dist"/><child link="f{i}_tip"/><origin xyz="0 0 0.03"/></joint>"""


def _gripper(tmp_path, extra_yaml=""):
    fingers = "".join(
        FINGER.format(i=i, x=0.025 * np.cos(a), y=0.025 * np.sin(a), yaw=a + np.pi / 2)
        for i, a in enumerate(np.arange(3) * 2 * np.pi / 3)
    )
    (tmp_path / "gripper3.urdf").write_text(GRIPPER_URDF.format(fingers=fingers))
    yaml = (
        textwrap.dedent(
            """\
        name: gripper3
        model: gripper3.urdf
        scale: 1.0
        keypoints:
          - {link: f0_tip, mano: 4}
          - {link: f1_tip, mano: 8}
          - {link: f2_tip, mano: 12}
          - {link: base, mano: 0}
        fingers:
          thumb: {joints: [f0_j0, f0_j1], links: [f0_prox, f0_dist]}
          index: {joints: [f1_j0, f1_j1], links: [f1_prox, f1_dist]}
          middle: {joints: [f2_j0, f2_j1], links: [f2_prox, f2_dist]}
        surface_points: 300
        """
        )
        + extra_yaml
    )
    (tmp_path / "gripper3.yaml").write_text(yaml)
    return tmp_path / "gripper3.yaml"


def test_third_hand_from_yaml_works_end_to_end(tmp_path, capsys):
    yaml = _gripper(tmp_path)
    png = tmp_path / "zero.png"
    assert cli_main(["hand", "check", str(yaml), "--png", str(png)]) == 0
    out = capsys.readouterr().out
    assert "f2_dist  [f2_j1: +0.000 .. +1.500]" in out and "keypoint MANO 12" in out
    assert png.stat().st_size > 10_000
    hand = load_hand(yaml)
    assert hand.dof == 12
    q = hand.zero(2)
    q[1, hand.joint_names.index("f0_j1")] = 1.0
    kp = hand.keypoints(q)
    assert not torch.allclose(kp[0, 0], kp[1, 0]) and torch.allclose(kp[0, 1:], kp[1, 1:])


@pytest.mark.parametrize(
    ("extra", "words"),
    [
        ("extra_joints: [f9_j0]\n", "unknown extra_joints ['f9_j0']; known: f0_j0, f0_j1"),
        ("couplings: [{joint: f0_j1, leader: nope}]\n", "unknown coupled joints ['nope']"),
    ],
)
def test_broken_yaml_lists_what_exists(tmp_path, extra, words):
    with pytest.raises(HandConfigError, match=words.replace("[", r"\[").replace("]", r"\]")):
        load_hand(_gripper(tmp_path, extra))


def test_unknown_link_joint_key_and_model_are_named(tmp_path):
    yaml = _gripper(tmp_path)
    text = yaml.read_text()
    cases = {
        "link": (
            text.replace("f2_tip, mano: 12", "f2_tipp, mano: 12"),
            r"unknown keypoint links \['f2_tipp'\]; known: base, f0_dist",
        ),
        "joint": (
            text.replace("[f1_j0, f1_j1]", "[f1_j0, f1_j9]"),
            r"joints in finger 'index' \['f1_j9'\]",
        ),
        "key": (text + "fingerz: {}\n", "fingerz"),
        "model": (text.replace("gripper3.urdf", "missing.urdf"), "no file at"),
        "order": (
            text.replace("thumb: {joints: [f0_j0", "little: {joints: [f0_j0"),
            "ordered thumb to little",
        ),
        "mano": (text.replace("mano: 12", "mano: 21"), "expected 0..20"),
    }
    for case, (broken, words) in cases.items():
        yaml.write_text(broken)
        with pytest.raises(HandConfigError, match=words):
            load_hand(yaml)
        assert case


def test_hand_check_reports_uncovered_joints_and_builtins_pass(tmp_path):
    yaml = _gripper(tmp_path)
    yaml.write_text(
        yaml.read_text().replace(
            "  middle: {joints: [f2_j0, f2_j1], links: [f2_prox, f2_dist]}\n", ""
        )
    )
    with pytest.raises(HandConfigError, match=r"in no finger.*f2_j0"):
        check_hand(yaml)
    for name in ("shadow", "allegro"):
        _, report = check_hand(name)
        assert report.endswith("ok")


def test_sharp_edge_points_keep_the_corners_and_follow_the_edges():
    half = np.array([0.01, 0.015, 0.02])
    points, normals = sharp_edge_points(trimesh.creation.box(2 * half), spacing=0.005, limit=500)
    on_edge = (np.isclose(np.abs(points), half, atol=1e-12).sum(1)) >= 2
    assert on_edge.all()  # every point on one of the 12 edges
    corners = np.array(list(itertools.product(*[(-h, h) for h in half])))
    assert np.linalg.norm(points[None] - corners[:, None], axis=-1).min(1).max() < 1e-12
    assert 60 <= len(points) <= 100  # 36 cm of edges, about 5 mm apart
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0)
    # the normal of an edge point bisects its two faces: outward, 45° from each
    assert np.all(np.einsum("ij,ij->i", normals, np.sign(points)) > 1.0)
    sparse = sharp_edge_points(trimesh.creation.box(2 * half), 0.005, limit=20)[0]
    assert 8 <= len(sparse) <= 20  # at most the limit, the corners still in
    assert len(sharp_edge_points(trimesh.creation.capsule(0.03, 0.01), 0.005, 100)[0]) == 0


def test_surface_samples_hold_the_corners_where_a_tilted_box_goes_deepest(tmp_path):
    """A box tilted over a surface first reaches it with a corner: the hand's surface samples
    (what penetration is measured on) include every corner of its boxes."""
    hand = load_hand(_gripper(tmp_path))
    q = hand.zero()
    q[0, 3], q[0, 4] = 0.3, 0.2  # the base turned about x and y
    points, normals = hand.surface(q)
    base = points[0][np.array(hand.surface_point_links) == "base"].numpy()
    frame = hand.link_transforms(q, ["base"])[0, 0].numpy()
    box = np.array(list(itertools.product((-0.03, 0.03), (-0.03, 0.03), (-0.01, 0.01))))
    corners = box @ frame[:3, :3].T + frame[:3, 3]
    assert np.linalg.norm(base[None] - corners[:, None], axis=-1).min(1).max() < 1e-9
    assert base[:, 2].min() == pytest.approx(corners[:, 2].min(), abs=1e-9)
    np.testing.assert_allclose(torch.linalg.vector_norm(normals[0], dim=-1).numpy(), 1.0, rtol=1e-6)
