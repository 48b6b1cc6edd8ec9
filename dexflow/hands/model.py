"""Reading a hand's model file (URDF or MJCF) into a kinematic chain plus collision geometry.

The chain is a pytorch-kinematics :class:`~pytorch_kinematics.chain.Chain`. MJCF files are
compiled by MuJoCo from their path, so ``<include>`` and mesh directories resolve as MuJoCo
resolves them; MJCF sites become frames of the chain (fingertip sites are common keypoints).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytorch_kinematics as pk
import trimesh
from pytorch_kinematics import frame as pk_frame
from pytorch_kinematics import transforms as pk_tf
from scipy.spatial.transform import RigidTransform, Rotation

from dexflow.errors import HandConfigError
from dexflow.hands.files import check_model_paths, resolve_model_path, urdf_mesh_path

__all__ = ["Geometry", "KinematicModel", "load_kinematic_model", "resolve_model_path"]


@dataclass
class Geometry:
    """A collision shape attached to a link.

    Attributes:
        link: Frame name in the chain.
        mesh: The shape as a triangle mesh, in the link frame.
        kind: 'box', 'sphere', 'capsule', 'cylinder' or 'mesh'.
        size: Box half-extents, or (radius, half-length) for capsules and cylinders, or
            (radius,) for spheres; empty for meshes.
        transform: (4, 4) shape frame in the link frame.
    """

    link: str
    mesh: trimesh.Trimesh
    kind: str
    size: tuple[float, ...]
    transform: np.ndarray


@dataclass
class KinematicModel:
    """A parsed hand model.

    Attributes:
        path: The model file.
        format: 'urdf' or 'mjcf'.
        chain: pytorch-kinematics chain rooted at the hand's root.
        joint_names: Actuated joints in chain order.
        lower: (J,) lower joint limits, radians.
        upper: (J,) upper joint limits.
        frames: Every frame (link, body or site) of the chain.
        parents: Frame name -> (parent frame, joint name or None).
        geometries: Collision shapes.
        mj_model: The compiled MuJoCo model (MJCF only).
        root: Root frame name.
    """

    path: Path
    format: str
    chain: pk.Chain
    joint_names: list[str]
    lower: np.ndarray
    upper: np.ndarray
    frames: list[str]
    parents: dict[str, tuple[str | None, str | None]]
    geometries: list[Geometry] = field(default_factory=list)
    mj_model: object | None = None
    root: str = ""


def _primitive(kind: str, size: tuple[float, ...], transform: np.ndarray) -> trimesh.Trimesh:
    if kind == "box":
        mesh = trimesh.creation.box(extents=2 * np.asarray(size))
    elif kind == "sphere":
        mesh = trimesh.creation.icosphere(subdivisions=2, radius=size[0])
    elif kind == "capsule":
        mesh = trimesh.creation.capsule(height=2 * size[1], radius=size[0], count=[16, 16])
    elif kind == "cylinder":
        mesh = trimesh.creation.cylinder(radius=size[0], height=2 * size[1], sections=24)
    else:
        raise HandConfigError(f"unsupported collision geometry '{kind}'")
    mesh.apply_transform(transform)
    return mesh


# ---------------------------------------------------------------------------------------- MJCF

_MJ_GEOM = {2: "sphere", 3: "capsule", 5: "cylinder", 6: "box", 7: "mesh"}


def _mjcf_chain(m, root_id: int) -> pk.Chain:
    """A pytorch-kinematics chain of the MuJoCo bodies below ``root_id``, sites included."""
    root = m.body(root_id)
    root_frame = pk_frame.Frame(
        root.name,
        link=pk_frame.Link(root.name, offset=pk_tf.Transform3d(rot=root.quat, pos=root.pos)),
        joint=pk_frame.Joint(),
    )
    children: dict[int, list[int]] = {}
    for body_id in range(1, m.nbody):
        children.setdefault(int(m.body_parentid[body_id]), []).append(body_id)
    sites: dict[int, list[int]] = {}
    for site_id in range(m.nsite):
        sites.setdefault(int(m.site_bodyid[site_id]), []).append(site_id)

    def grow(parent_frame, body_id: int) -> None:
        for child_id in children.get(body_id, []):
            body = m.body(child_id)
            if body.jntnum[0] > 1:
                raise HandConfigError(
                    f"MJCF body '{body.name}' has {body.jntnum[0]} joints; "
                    "dexflow supports one joint per body"
                )
            if body.jntnum[0] == 1:
                joint = m.joint(int(body.jntadr[0]))
                if joint.type[0] not in (2, 3):
                    raise HandConfigError(f"MJCF joint '{joint.name}': only hinge and slide joints")
                child_joint = pk_frame.Joint(
                    joint.name,
                    offset=pk_tf.Transform3d(pos=joint.pos),
                    axis=joint.axis,
                    joint_type=pk.JOINT_TYPE_MAP[joint.type[0]],
                    limits=(joint.range[0], joint.range[1]),
                )
            else:
                child_joint = pk_frame.Joint(body.name + "_fixed_joint")
            link = pk_frame.Link(body.name, offset=pk_tf.Transform3d(rot=body.quat, pos=body.pos))
            child = pk_frame.Frame(name=body.name, link=link, joint=child_joint)
            parent_frame.children = [*parent_frame.children, child]
            grow(child, child_id)
        for site_id in sites.get(body_id, []):
            site = m.site(site_id)
            link = pk_frame.Link(site.name, offset=pk_tf.Transform3d(rot=site.quat, pos=site.pos))
            parent_frame.children = [
                *parent_frame.children,
                pk_frame.Frame(name=site.name, link=link),
            ]

    grow(root_frame, root_id)
    return pk.Chain(root_frame)


def _mjcf_geometries(m, body_ids: set[int]) -> list[Geometry]:
    out = []
    for g in range(m.ngeom):
        body_id = int(m.geom_bodyid[g])
        if body_id not in body_ids or (m.geom_contype[g] == 0 and m.geom_conaffinity[g] == 0):
            continue
        kind = _MJ_GEOM.get(int(m.geom_type[g]))
        if kind is None:
            continue
        rotation = Rotation.from_quat(m.geom_quat[g], scalar_first=True)  # MuJoCo: w, x, y, z
        transform = RigidTransform.from_components(m.geom_pos[g], rotation).as_matrix()
        if kind == "mesh":
            mesh_id = int(m.geom_dataid[g])
            va, vn = int(m.mesh_vertadr[mesh_id]), int(m.mesh_vertnum[mesh_id])
            fa, fn = int(m.mesh_faceadr[mesh_id]), int(m.mesh_facenum[mesh_id])
            mesh = trimesh.Trimesh(
                m.mesh_vert[va : va + vn].copy(), m.mesh_face[fa : fa + fn].copy()
            )
            mesh.apply_transform(transform)
            size: tuple[float, ...] = ()
        else:
            size = {"box": tuple(m.geom_size[g]), "sphere": (m.geom_size[g][0],)}.get(
                kind, (m.geom_size[g][0], m.geom_size[g][1])
            )
            size = tuple(float(s) for s in size)
            mesh = _primitive(kind, size, transform)
        out.append(Geometry(m.body(body_id).name, mesh, kind, size, transform))
    return out


def _load_mjcf(path: Path, root: str) -> KinematicModel:
    import mujoco

    try:
        m = mujoco.MjModel.from_xml_path(str(path))
    except Exception as exc:
        raise HandConfigError(f"{path}: MuJoCo cannot compile the MJCF: {exc}") from exc
    bodies = [m.body(i).name for i in range(m.nbody)]
    if root:
        if root not in bodies:
            raise HandConfigError(f"{path}: unknown root body '{root}'; known: {bodies}")
        root_id = bodies.index(root)
    else:
        root_id = 1 if m.nbody > 1 else 0
    chain = _mjcf_chain(m, root_id)
    subtree = {root_id}
    for body_id in range(m.nbody):
        parent = int(m.body_parentid[body_id])
        if parent in subtree and body_id != root_id:
            subtree.add(body_id)
    return _finish(path, "mjcf", chain, _mjcf_geometries(m, subtree), mj_model=m)


# ---------------------------------------------------------------------------------------- URDF


def _origin(element) -> np.ndarray:
    origin = element.find("origin") if element is not None else None
    xyz = (
        [float(v) for v in origin.get("xyz", "0 0 0").split()] if origin is not None else [0, 0, 0]
    )
    rpy = (
        [float(v) for v in origin.get("rpy", "0 0 0").split()] if origin is not None else [0, 0, 0]
    )
    # URDF rpy: roll, pitch, yaw about the fixed x, y, z axes (extrinsic), R = Rz Ry Rx.
    return RigidTransform.from_components(xyz, Rotation.from_euler("xyz", rpy)).as_matrix()


def _urdf_geometries(path: Path) -> list[Geometry]:
    out = []
    root = ET.parse(path).getroot()
    for link in root.iter("link"):
        for collision in link.findall("collision"):
            transform = _origin(collision)
            geom = collision.find("geometry")
            shape = next(iter(geom), None) if geom is not None else None
            if shape is None:
                continue
            if shape.tag == "box":
                size = tuple(float(v) / 2 for v in shape.get("size").split())
                mesh = _primitive("box", size, transform)
            elif shape.tag == "sphere":
                size = (float(shape.get("radius")),)
                mesh = _primitive("sphere", size, transform)
            elif shape.tag in ("cylinder", "capsule"):
                size = (float(shape.get("radius")), float(shape.get("length")) / 2)
                mesh = _primitive(shape.tag, size, transform)
            elif shape.tag == "mesh":
                mesh_path = urdf_mesh_path(shape.get("filename"), path.parent)
                if not mesh_path.is_file():
                    raise HandConfigError(
                        f"{path}: link '{link.get('name')}' collision mesh "
                        f"'{shape.get('filename')}' not found at {mesh_path}"
                    )
                mesh = trimesh.load(mesh_path, force="mesh")
                scale = [float(v) for v in shape.get("scale", "1 1 1").split()]
                mesh.apply_scale(scale)
                mesh.apply_transform(transform)
                size = ()
            else:
                continue
            out.append(Geometry(link.get("name"), mesh, shape.tag, size, transform))
    return out


def _load_urdf(path: Path, root: str) -> KinematicModel:
    try:
        chain = pk.build_chain_from_urdf(path.read_bytes())
    except Exception as exc:
        raise HandConfigError(f"{path}: cannot parse the URDF: {exc}") from exc
    if root and chain._root.name != root:
        raise HandConfigError(
            f"{path}: root '{root}' must be the URDF's root link "
            f"'{chain._root.name}' (or left empty)"
        )
    return _finish(path, "urdf", chain, _urdf_geometries(path))


# ------------------------------------------------------------------------------------- common


def _finish(path: Path, fmt: str, chain: pk.Chain, geometries, mj_model=None) -> KinematicModel:
    joint_names = list(chain.get_joint_parameter_names())
    low, high = chain.get_joint_limits()
    parents: dict[str, tuple[str | None, str | None]] = {}

    def walk(frame, parent):
        joint = frame.joint.name if frame.joint.joint_type != "fixed" else None
        parents[frame.name] = (parent, joint)
        for child in frame.children:
            walk(child, frame.name)

    walk(chain._root, None)
    frames = list(parents)
    known = set(frames)
    geometries = [g for g in geometries if g.link in known]
    return KinematicModel(
        path=path,
        format=fmt,
        chain=chain,
        joint_names=joint_names,
        lower=np.asarray(low, dtype=np.float64),
        upper=np.asarray(high, dtype=np.float64),
        frames=frames,
        parents=parents,
        geometries=geometries,
        mj_model=mj_model,
        root=chain._root.name,
    )


def load_kinematic_model(path: str | Path, root: str = "") -> KinematicModel:
    """Parse a URDF (``.urdf``) or MJCF (``.xml``/``.mjcf``) hand model.

    Every file the model names (meshes, includes, asset directories) is first checked to lie
    inside the model's folder (:func:`dexflow.hands.files.check_model_paths`), so neither
    trimesh nor MuJoCo opens a file outside it.

    Raises:
        HandConfigError: the format is unknown, a named file lies outside the model's folder,
            or the model does not parse.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".urdf", ".xml", ".mjcf"):
        raise HandConfigError(
            f"{path}: unknown model format '{suffix}'; expected .urdf, .xml or .mjcf"
        )
    check_model_paths(path)
    return _load_urdf(path, root) if suffix == ".urdf" else _load_mjcf(path, root)
