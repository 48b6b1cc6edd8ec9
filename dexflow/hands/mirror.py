"""A left hand model written as its mirror image, a right hand (``dexflow hand init --mirror``).

The mirror is the reflection ``x -> -x`` of every link frame, visual and collision shape and
inertia (:func:`mirror_model`): joint axes and origins are reflected and conjugated so that the
mirrored model at ``q`` is the reflection of the original at ``q``; meshes are written mirrored
(with their faces reversed, so that normals still point out) beside the new URDF.
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from dexflow.hands.model import (
    KinematicModel,
    _origin,
)
from dexflow.hands.spec import CouplingSpec
from dexflow.hands.tree import Kinematics

__all__ = ["mirror_model"]

_MIRROR = np.diag([-1.0, 1.0, 1.0])
_MIRROR4 = np.diag([-1.0, 1.0, 1.0, 1.0])


def _fmt(values) -> str:
    return " ".join(f"{float(v) + 0.0:.9g}" for v in values)


def _urdf_origin(parent: ET.Element, transform: np.ndarray) -> None:
    rpy = Rotation.from_matrix(transform[:3, :3]).as_euler("xyz")  # about the fixed x, y, z
    ET.SubElement(parent, "origin", xyz=_fmt(transform[:3, 3]), rpy=_fmt(rpy))


def _urdf_inertial(inertial: ET.Element) -> tuple[np.ndarray, float, np.ndarray]:
    mass, inertia = inertial.find("mass"), inertial.find("inertia")
    get = {} if inertia is None else inertia.attrib
    xx, xy, xz, yy, yz, zz = (
        float(get.get(k, 0.0)) for k in ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")
    )
    tensor = np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])
    return _origin(inertial), float(0.0 if mass is None else mass.get("value", 0.0)), tensor


def _physics(model: KinematicModel) -> tuple[dict, dict]:
    """What a simulator needs and the kinematic model leaves out, from the model file.

    Returns:
        Per link its inertial ``(pose (4, 4) in the link frame, mass, inertia (3, 3) in that
        pose)`` (links without one are left out), and per joint its ``(effort, velocity)``.
    """
    inertials, limits = {}, {}
    if model.format == "urdf":
        root = ET.parse(model.path).getroot()
        for link in root.iter("link"):
            inertial = link.find("inertial")
            if inertial is not None:
                inertials[link.get("name")] = _urdf_inertial(inertial)
        for joint in root.iter("joint"):
            limit = joint.find("limit")
            if limit is not None:
                limits[joint.get("name")] = (
                    float(limit.get("effort", 10.0)),
                    float(limit.get("velocity", 3.14)),
                )
    else:
        m = model.mj_model
        for b in range(m.nbody):
            if m.body_mass[b] > 0:
                pose = np.eye(4)
                pose[:3, :3] = Rotation.from_quat(m.body_iquat[b], scalar_first=True).as_matrix()
                pose[:3, 3] = m.body_ipos[b]
                inertials[m.body(b).name] = (
                    pose,
                    float(m.body_mass[b]),
                    np.diag(m.body_inertia[b]),
                )
        for a in range(m.nu):
            if m.actuator_trntype[a] == 0 and m.actuator_forcelimited[a]:
                effort = float(np.abs(m.actuator_forcerange[a]).max())
                limits[m.joint(int(m.actuator_trnid[a][0])).name] = (effort, 3.14)
    return inertials, limits


def _inertial(link: ET.Element, pose: np.ndarray, mass: float, tensor: np.ndarray) -> None:
    inertial = ET.SubElement(link, "inertial")
    _urdf_origin(inertial, pose)
    ET.SubElement(inertial, "mass", value=_fmt([mass]))
    names = ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")
    cells = (tensor[0, 0], tensor[0, 1], tensor[0, 2], tensor[1, 1], tensor[1, 2], tensor[2, 2])
    ET.SubElement(inertial, "inertia", {n: _fmt([v]) for n, v in zip(names, cells, strict=True)})


def mirror_model(
    model: KinematicModel, out_path: str | Path, couplings: list[CouplingSpec] | None = None
) -> Path:
    """Write the mirror image (``x -> -x`` in the root frame) of a hand model as a URDF.

    Every frame ``T`` (at zero joints) becomes ``M T M`` with ``M = diag(-1, 1, 1)``, again a
    rigid transform; a revolute axis ``a`` (in its child frame) becomes ``-M a`` and a
    prismatic one ``M a``, so that every joint keeps its name, angle and limits and
    ``FK'(q) = M FK(q) M``. Collision shapes are reflected in their link frames (primitives are
    symmetric; meshes are written as OBJ files in ``<stem>_meshes/``), inertials too (pose
    ``M T M``, inertia ``M I M``); joint efforts and velocities are kept (an MJCF's from its
    joint actuators). Couplings become ``<mimic>`` tags. Visual shapes and joint dynamics are
    not carried over.

    Args:
        model: A parsed URDF or MJCF hand.
        out_path: The URDF to write.
        couplings: Joints tied to others.

    Returns:
        ``out_path``.
    """
    from dexflow.io.atomic import atomic_path

    out_path = Path(out_path)
    mesh_dir = out_path.parent / f"{out_path.stem}_meshes"
    kin = Kinematics(model)
    zero = kin.transforms(np.zeros(len(kin.joint_names)))[0]
    world = {f: _MIRROR4 @ t @ _MIRROR4 for f, t in zip(kin.frames, zero, strict=True)}
    limits = dict(zip(kin.joint_names, zip(model.lower, model.upper, strict=True), strict=True))
    mimic = {c.joint: c for c in couplings or []}
    inertials, efforts = _physics(model)
    shapes: dict[str, list] = {}
    for g in model.geometries:
        shapes.setdefault(g.link, []).append(g)
    unsafe = re.compile(r"[^A-Za-z0-9_.-]")
    robot = ET.Element("robot", name=f"{model.path.stem}_mirrored")
    for frame in kin.frames:
        link = ET.SubElement(robot, "link", name=frame)
        if frame in inertials:  # mass and inertia reflected too: I' = M I M in M T M
            pose, mass, tensor = inertials[frame]
            _inertial(link, _MIRROR4 @ pose @ _MIRROR4, mass, _MIRROR @ tensor @ _MIRROR)
        elif model.format == "mjcf":  # a site or a massless body: as dexflow hand export
            _inertial(link, np.eye(4), 1e-5, np.eye(3) * 1e-9)
        for k, g in enumerate(shapes.get(frame, [])):
            collision = ET.SubElement(link, "collision")
            geometry = ET.Element("geometry")
            if g.kind == "mesh":  # vertices already in the link frame
                mesh = trimesh.Trimesh(
                    g.mesh.vertices @ _MIRROR, g.mesh.faces[:, ::-1], process=False
                )
                mesh_path = mesh_dir / f"{unsafe.sub('_', frame)}_{k}.obj"
                with atomic_path(mesh_path) as tmp:
                    tmp.write_text(trimesh.exchange.obj.export_obj(mesh, include_normals=False))
                _urdf_origin(collision, np.eye(4))
                ET.SubElement(geometry, "mesh", filename=f"{mesh_dir.name}/{mesh_path.name}")
            else:
                _urdf_origin(collision, _MIRROR4 @ g.transform @ _MIRROR4)
                if g.kind == "box":
                    ET.SubElement(geometry, "box", size=_fmt(2 * np.asarray(g.size)))
                elif g.kind == "sphere":
                    ET.SubElement(geometry, "sphere", radius=_fmt(g.size[:1]))
                else:  # capsule, cylinder: (radius, half-length)
                    ET.SubElement(
                        geometry, g.kind, radius=_fmt(g.size[:1]), length=_fmt([2 * g.size[1]])
                    )
            collision.append(geometry)
        parent, joint = kin.parents[frame]
        if parent is None:
            continue
        if joint is None:
            element = ET.SubElement(robot, "joint", name=f"{frame}_fixed", type="fixed")
        else:
            kind, axis = kin.joint(joint)
            element = ET.SubElement(robot, "joint", name=joint, type=kind)
            ET.SubElement(
                element, "axis", xyz=_fmt(-_MIRROR @ axis if kind == "revolute" else _MIRROR @ axis)
            )
            lower, upper = limits[joint]
            effort, velocity = efforts.get(joint, (10.0, 3.14))
            ET.SubElement(
                element,
                "limit",
                lower=_fmt([lower]),
                upper=_fmt([upper]),
                effort=_fmt([effort]),
                velocity=_fmt([velocity]),
            )
            if joint in mimic:
                c = mimic[joint]
                ET.SubElement(
                    element,
                    "mimic",
                    joint=c.leader,
                    multiplier=_fmt([c.ratio]),
                    offset=_fmt([c.offset]),
                )
        ET.SubElement(element, "parent", link=parent)
        ET.SubElement(element, "child", link=frame)
        _urdf_origin(element, np.linalg.inv(world[parent]) @ world[frame])
    ET.indent(robot)
    header = (
        '<?xml version="1.0"?>\n'
        f"<!-- The mirror image (x -> -x) of {model.path.name} ({model.format.upper()}), written "
        "by dexflow hand init: the same link and joint names, angles and limits; collision "
        "shapes and inertials reflected, no visuals. -->\n"
    )
    with atomic_path(out_path) as tmp:
        tmp.write_text(header + ET.tostring(robot, encoding="unicode") + "\n")
    return out_path
