"""Writing an MJCF hand as a URDF that pybullet loads (pybullet cannot read the MJCF).

Every body below the hand's root becomes a link with the same name and frame; hinge joints
become revolute joints, bodies without joints fixed ones, sites fixed child links. Collision
shapes are kept as primitives (pybullet's ``<capsule>`` included); mesh shapes are written as
OBJ files beside the URDF. A link ``hand_root`` carries the root body's offset, so that with the
base at the identity every link frame equals :meth:`RobotHand.link_transforms` at zero base.
"""

from __future__ import annotations

import warnings
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from dexflow.errors import HandConfigError
from dexflow.hands.model import KinematicModel
from dexflow.io.atomic import atomic_path

__all__ = ["ROOT_LINK", "export_urdf"]

ROOT_LINK = "hand_root"
_DEFAULT_EFFORT = 10.0
_DEFAULT_VELOCITY = 3.14


def _fmt(values) -> str:
    return " ".join(f"{float(v):.9g}" for v in values)


def _origin(parent: ET.Element, pos, quat_wxyz) -> None:
    with warnings.catch_warnings():  # at gimbal lock any of the equivalent angle sets will do
        warnings.filterwarnings("ignore", "Gimbal lock", UserWarning)
        rpy = Rotation.from_quat(quat_wxyz, scalar_first=True).as_euler("xyz")
    ET.SubElement(parent, "origin", xyz=_fmt(pos), rpy=_fmt(rpy))


def _inertial(link: ET.Element, mass: float, pos=(0, 0, 0), quat=(1, 0, 0, 0), diag=(1e-6,) * 3):
    inertial = ET.SubElement(link, "inertial")
    _origin(inertial, pos, quat)
    ET.SubElement(inertial, "mass", value=f"{max(float(mass), 0.0):.9g}")
    ixx, iyy, izz = (max(float(d), 1e-9) for d in diag)
    ET.SubElement(
        inertial,
        "inertia",
        ixx=f"{ixx:.9g}",
        iyy=f"{iyy:.9g}",
        izz=f"{izz:.9g}",
        ixy="0",
        ixz="0",
        iyz="0",
    )


def _geometry(m, g: int, mesh_dir: Path, rel_dir: str) -> ET.Element | None:
    kind = int(m.geom_type[g])
    size = m.geom_size[g]
    geometry = ET.Element("geometry")
    if kind == 6:
        ET.SubElement(geometry, "box", size=_fmt(2 * size))
    elif kind == 2:
        ET.SubElement(geometry, "sphere", radius=f"{size[0]:.9g}")
    elif kind == 3:
        ET.SubElement(geometry, "capsule", radius=f"{size[0]:.9g}", length=f"{2 * size[1]:.9g}")
    elif kind == 5:
        ET.SubElement(geometry, "cylinder", radius=f"{size[0]:.9g}", length=f"{2 * size[1]:.9g}")
    elif kind == 7:
        mesh_id = int(m.geom_dataid[g])
        va, vn = int(m.mesh_vertadr[mesh_id]), int(m.mesh_vertnum[mesh_id])
        fa, fn = int(m.mesh_faceadr[mesh_id]), int(m.mesh_facenum[mesh_id])
        name = f"geom_{g:03d}.obj"
        lines = [f"v {_fmt(v)}" for v in m.mesh_vert[va : va + vn]]
        lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in m.mesh_face[fa : fa + fn]]
        with atomic_path(mesh_dir / name) as tmp:
            tmp.write_text("\n".join(lines) + "\n")
        ET.SubElement(geometry, "mesh", filename=f"{rel_dir}/{name}")
    else:
        return None
    return geometry


def export_urdf(model: KinematicModel, out_path: str | Path) -> Path:
    """Write ``model`` (an MJCF hand) as a URDF at ``out_path``; meshes go to ``<stem>_meshes/``.

    Bodies keep MuJoCo's masses and inertias as they are (a massless body stays massless:
    :func:`dexflow.hands.physics.physics_urdf` gives it the documented default); the frames the
    export adds (the root link, one per site) weigh 10 mg.

    Returns:
        ``out_path``.
    """
    if model.format != "mjcf" or model.mj_model is None:
        raise HandConfigError(f"{model.path}: only MJCF hands need exporting; use the URDF itself")
    m = model.mj_model
    out_path = Path(out_path)
    mesh_dir = out_path.parent / f"{out_path.stem}_meshes"
    bodies = {m.body(i).name: i for i in range(m.nbody)}
    root_id = bodies[model.root]
    efforts = {}
    for a in range(m.nu):
        if m.actuator_trntype[a] == 0:  # actuator on a joint
            efforts[int(m.actuator_trnid[a][0])] = float(np.abs(m.actuator_forcerange[a]).max())

    robot = ET.Element("robot", name=model.path.stem)
    root_link = ET.SubElement(robot, "link", name=ROOT_LINK)
    _inertial(root_link, 1e-5)

    def add_body(body_id: int, parent: str) -> None:
        body = m.body(body_id)
        link = ET.SubElement(robot, "link", name=body.name)
        _inertial(
            link,
            m.body_mass[body_id],
            m.body_ipos[body_id],
            m.body_iquat[body_id],
            m.body_inertia[body_id],
        )
        for g in range(m.ngeom):
            if int(m.geom_bodyid[g]) != body_id:
                continue
            if m.geom_contype[g] == 0 and m.geom_conaffinity[g] == 0:
                continue
            geometry = _geometry(m, g, mesh_dir, mesh_dir.name)
            if geometry is None:
                continue
            for tag in ("collision", "visual"):
                element = ET.SubElement(link, tag)
                _origin(element, m.geom_pos[g], m.geom_quat[g])
                element.append(geometry)
        if body.jntnum[0] == 1 and body_id != root_id:
            j = int(body.jntadr[0])
            joint = m.joint(j)
            if np.abs(joint.pos).max() > 1e-12:
                raise HandConfigError(
                    f"MJCF joint '{joint.name}' is offset from its body frame; "
                    "URDF export needs joints at body origins"
                )
            kind = {3: "revolute", 2: "prismatic"}.get(int(joint.type[0]))
            if kind is None:
                raise HandConfigError(f"MJCF joint '{joint.name}': only hinge and slide joints")
            element = ET.SubElement(robot, "joint", name=joint.name, type=kind)
            ET.SubElement(element, "axis", xyz=_fmt(joint.axis))
            ET.SubElement(
                element,
                "limit",
                lower=f"{joint.range[0]:.9g}",
                upper=f"{joint.range[1]:.9g}",
                effort=f"{efforts.get(j, _DEFAULT_EFFORT):.9g}",
                velocity=f"{_DEFAULT_VELOCITY}",
            )
        else:
            element = ET.SubElement(robot, "joint", name=f"{body.name}_fixed", type="fixed")
        ET.SubElement(element, "parent", link=parent)
        ET.SubElement(element, "child", link=body.name)
        _origin(element, m.body_pos[body_id], m.body_quat[body_id])
        for s in range(m.nsite):
            if int(m.site_bodyid[s]) == body_id:
                site = m.site(s)
                site_link = ET.SubElement(robot, "link", name=site.name)
                _inertial(site_link, 1e-5)
                site_joint = ET.SubElement(robot, "joint", name=f"{site.name}_fixed", type="fixed")
                ET.SubElement(site_joint, "parent", link=body.name)
                ET.SubElement(site_joint, "child", link=site.name)
                _origin(site_joint, m.site_pos[s], m.site_quat[s])
        for child in range(m.nbody):
            if child != body_id and int(m.body_parentid[child]) == body_id:
                add_body(child, body.name)

    add_body(root_id, ROOT_LINK)
    ET.indent(robot)
    text = ET.tostring(robot, encoding="unicode")
    header = f'<?xml version="1.0"?>\n<!-- Exported by dexflow from {model.path.name}. -->\n'
    with atomic_path(out_path) as tmp:
        tmp.write_text(header + text + "\n")
    return out_path
