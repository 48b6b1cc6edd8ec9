"""Hand models built on the fly for the tests: small URDF and MJCF hands, and the shapes public
models come in (a root link named ``world``, links named like scene objects, missing or invalid
inertias, an MJCF scene with its own world and includes, a left hand).

The hands are described in a right hand's canonical frame (z along the fingers, y towards the
thumb, x out of the palm, as :func:`dexflow.human.keypoints.wrist_frame`); their left versions
are reflected across the x-z plane here, independently of the x -> -x mirror that ``hand init``
writes.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation


@dataclass
class _Joint:
    name: str
    parent: str
    child: str
    xyz: tuple[float, float, float]
    rot: np.ndarray | None = None  # child frame in the parent frame
    axis: tuple[float, float, float] | None = None  # None: fixed
    limits: tuple[float, float] = (0.0, 1.6)
    mimic: tuple[str, float] | None = None


_REFLECT_Y = np.diag([1.0, -1.0, 1.0])
MIRROR = np.diag([-1.0, 1.0, 1.0])  # how dexflow mirrors a left-hand sequence (x -> -x)


def urdf_text(name: str, boxes: dict[str, list], joints: list[_Joint], side: str = "right") -> str:
    """A URDF of box links; ``side='left'`` reflects the whole hand across the x-z plane."""
    m = _REFLECT_Y if side == "left" else np.eye(3)
    out = [f'<?xml version="1.0"?>\n<robot name="{name}">']
    for link, shapes in boxes.items():
        body = "".join(
            f'<collision><origin xyz="{" ".join(map(str, m @ np.asarray(c)))}"/>'
            f'<geometry><box size="{" ".join(map(str, s))}"/></geometry></collision>'
            for c, s in shapes
        )
        if shapes:  # the first box, solid, 1000 kg/m³; a tilted inertia (ixy) to reflect
            (c, size) = shapes[0]
            mass = 1000.0 * float(np.prod(size))
            a, b, h = size
            inertia = (
                f'ixx="{mass * (b * b + h * h) / 12}" iyy="{mass * (a * a + h * h) / 12}" '
                f'izz="{mass * (a * a + b * b) / 12}" ixy="{mass * a * b / 50}" ixz="0" iyz="0"'
            )
            body += (
                f'<inertial><origin xyz="{" ".join(map(str, m @ np.asarray(c)))}"/>'
                f'<mass value="{mass}"/><inertia {inertia}/></inertial>'
            )
        out.append(f'  <link name="{link}">{body}</link>')
    for j in joints:
        rot = m @ (np.eye(3) if j.rot is None else j.rot) @ m
        rpy = " ".join(map(str, Rotation.from_matrix(rot).as_euler("xyz")))
        xyz = " ".join(map(str, m @ np.asarray(j.xyz)))
        kind = "fixed" if j.axis is None else "revolute"
        inner = f'<parent link="{j.parent}"/><child link="{j.child}"/>'
        inner += f'<origin xyz="{xyz}" rpy="{rpy}"/>'
        if j.axis is not None:  # a reflected hinge keeps its angle about -M a
            axis = -m @ np.asarray(j.axis) if side == "left" else np.asarray(j.axis)
            inner += f'<axis xyz="{" ".join(map(str, axis))}"/>'
            inner += f'<limit lower="{j.limits[0]}" upper="{j.limits[1]}" effort="1" velocity="1"/>'
        if j.mimic is not None:
            inner += f'<mimic joint="{j.mimic[0]}" multiplier="{j.mimic[1]}"/>'
        out.append(f'  <joint name="{j.name}" type="{kind}">{inner}</joint>')
    out.append("</robot>\n")
    return "\n".join(out)


def _finger(
    prefix: str,
    parent: str,
    base: tuple[float, float, float],
    lengths: tuple[float, float, float],
    rot: np.ndarray | None = None,
    abduction: bool = True,
    tip_link: bool = False,
    mimic: float | None = None,
    flex_axis: tuple[float, float, float] = (0.0, 1.0, 0.0),
) -> tuple[dict[str, list], list[_Joint]]:
    """A finger along its frame's z: abduction about x, then three flexion joints about y
    (the tip turns towards +x), box links, optionally a tip link and a mimicking distal joint."""
    w = 0.016
    parts = zip(("proximal", "middle", "distal"), lengths, strict=True)
    boxes = {f"{prefix}_{part}": [((0, 0, h / 2), (w, w, h))] for part, h in parts}
    joints = []
    first_parent = parent
    if abduction:
        boxes[f"{prefix}_knuckle"] = []
        joints.append(
            _Joint(f"{prefix}_abd", parent, f"{prefix}_knuckle", base, rot, (1, 0, 0), (-0.3, 0.3))
        )
        first_parent, base, rot = f"{prefix}_knuckle", (0, 0, 0), None
    joints += [
        _Joint(f"{prefix}_mcp", first_parent, f"{prefix}_proximal", base, rot, flex_axis),
        _Joint(f"{prefix}_pip", f"{prefix}_proximal", f"{prefix}_middle", (0, 0, lengths[0]),
               axis=flex_axis),
        _Joint(f"{prefix}_dip", f"{prefix}_middle", f"{prefix}_distal", (0, 0, lengths[1]),
               axis=flex_axis, mimic=None if mimic is None else (f"{prefix}_pip", mimic)),
    ]  # fmt: skip
    if tip_link:
        boxes[f"{prefix}_tip"] = []
        joints.append(_Joint(f"{prefix}_tipj", f"{prefix}_distal", f"{prefix}_tip",
                             (0, 0, lengths[2])))  # fmt: skip
    return boxes, joints


def _thumb_rotation() -> np.ndarray:
    """Thumb frame: z forward and towards the index side, flexing (x) across the palm."""
    z = np.array([0.35, 0.6, 0.72])
    z /= np.linalg.norm(z)
    x = np.array([1.0, -0.8, 0.0])
    x -= (x @ z) * z
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=-1)


PALM = {"palm": [((0, 0, 0.045), (0.02, 0.075, 0.09))]}
THUMB = dict(base=(0.012, 0.03, 0.02), lengths=(0.045, 0.033, 0.03), rot=_thumb_rotation())


def hand4(tmp_path, side: str = "right"):
    """Thumb, index, middle, ring (no little finger); tips only from the collision boxes."""
    boxes, joints = dict(PALM), []
    for prefix, spec in (
        ("th", THUMB),
        ("if", dict(base=(0, 0.024, 0.09), lengths=(0.045, 0.027, 0.024))),
        ("mf", dict(base=(0, 0.0, 0.09), lengths=(0.048, 0.029, 0.025))),
        ("rf", dict(base=(0, -0.024, 0.088), lengths=(0.045, 0.027, 0.024))),
    ):
        b, j = _finger(prefix, "palm", **spec)
        boxes |= b
        joints += j
    path = tmp_path / f"hand4_{side}.urdf"
    path.write_text(urdf_text("hand4", boxes, joints, side))
    return path


def hand5(tmp_path, side: str = "right"):
    """Five fingers on a palm behind a wrist joint; tip links; each distal joint mimics the
    middle one (0.7)."""
    boxes = {"forearm": [((0, 0, -0.06), (0.04, 0.06, 0.1))], **PALM}
    joints = [_Joint("wrist", "forearm", "palm", (0, 0, 0), axis=(0, 1, 0), limits=(-0.6, 0.6))]
    for prefix, spec in (
        ("th", dict(THUMB)),
        ("if", dict(base=(0, 0.027, 0.09), lengths=(0.045, 0.027, 0.024), mimic=0.7)),
        ("mf", dict(base=(0, 0.009, 0.09), lengths=(0.048, 0.029, 0.025), mimic=0.7)),
        ("rf", dict(base=(0, -0.009, 0.088), lengths=(0.045, 0.027, 0.024), mimic=0.7)),
        ("lf", dict(base=(0, -0.027, 0.082), lengths=(0.035, 0.021, 0.02), mimic=0.7)),
    ):
        b, j = _finger(prefix, "palm", tip_link=True, **spec)
        boxes |= b
        joints += j
    path = tmp_path / f"hand5_{side}.urdf"
    path.write_text(urdf_text("hand5", boxes, joints, side))
    return path


def gripper(tmp_path):
    """Three fingers: two side by side flexing towards +x, one opposite them flexing to -x."""
    boxes = {"palm": [((0.02, 0, 0.025), (0.06, 0.06, 0.05))]}
    joints = []
    for prefix, base, axis in (
        ("a", (0, 0.02, 0.05), (0, 1, 0)),
        ("b", (0, -0.02, 0.05), (0, 1, 0)),
        ("t", (0.04, 0, 0.05), (0, -1, 0)),
    ):
        b, j = _finger(prefix, "palm", base, (0.05, 0.045, 0.0), abduction=False,
                       tip_link=True, flex_axis=axis)  # fmt: skip
        del b[f"{prefix}_distal"]  # two flexion joints: proximal, middle, then the tip
        j = [x for x in j if x.name != f"{prefix}_dip"]
        j[-1] = replace(j[-1], parent=f"{prefix}_middle", xyz=(0, 0, 0.045))
        boxes |= b
        joints += j
    path = tmp_path / "gripper.urdf"
    path.write_text(urdf_text("gripper", boxes, joints))
    return path


MJCF_HAND = """
<mujoco model="mjhand">
  <compiler angle="radian"/>
  <equality><joint joint1="a2" joint2="a1" polycoef="0.1 0.8 0 0 0"/></equality>
  <tendon>
    <fixed name="couple_b" limited="true" range="-0.001 0.001">
      <joint joint="b1" coef="0.01"/><joint joint="b2" coef="-0.008"/>
    </fixed>
    <fixed name="loose" limited="true" range="-0.03 0.03">
      <joint joint="t1" coef="0.01"/><joint joint="t2" coef="0.01"/>
    </fixed>
  </tendon>
  <worldbody>
    <body name="object" pos="0.3 0 0"><freejoint/><geom type="sphere" size="0.03"/></body>
    <body name="mount">
      <body name="palm">
        <joint name="wrist" type="hinge" axis="1 0 0" range="-0.5 0.5"/>
        <geom type="box" size="0.03 0.03 0.025" pos="0.02 0 0.025"/>
        <body name="a_prox" pos="0 0.02 0.05">
          <joint name="a1" type="hinge" axis="0 1 0" range="0 1.6"/>
          <geom type="capsule" fromto="0 0 0 0 0 0.05" size="0.008"/>
          <body name="a_dist" pos="0 0 0.05">
            <joint name="a2" type="hinge" axis="0 1 0" range="0 1.6"/>
            <geom type="capsule" fromto="0 0 0 0 0 0.04" size="0.008"/>
            <site name="a_tip" pos="0 0 0.048"/>
          </body>
        </body>
        <body name="b_prox" pos="0 -0.02 0.05">
          <joint name="b1" type="hinge" axis="0 1 0" range="0 1.6"/>
          <geom type="capsule" fromto="0 0 0 0 0 0.05" size="0.008"/>
          <body name="b_dist" pos="0 0 0.05">
            <joint name="b2" type="hinge" axis="0 1 0" range="0 1.6"/>
            <geom type="capsule" fromto="0 0 0 0 0 0.04" size="0.008"/>
          </body>
        </body>
        <body name="t_prox" pos="0.04 0.005 0.05">
          <joint name="t1" type="hinge" axis="0 -1 0" range="0 1.6"/>
          <geom type="capsule" fromto="0 0 0 0 0 0.05" size="0.008"/>
          <body name="t_dist" pos="0 0 0.05">
            <joint name="t2" type="hinge" axis="0 -1 0" range="0 1.6"/>
            <geom type="capsule" fromto="0 0 0 0 0 0.04" size="0.008"/>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
</mujoco>
"""


# ------------------------------------------------------------ hands shaped like public models


def _rewrite(path: Path, out: Path, edit) -> Path:
    """Write ``out``: the URDF at ``path`` with ``edit(root)`` applied to its XML tree."""
    tree = ET.parse(path)
    edit(tree.getroot())
    out.write_text('<?xml version="1.0"?>\n' + ET.tostring(tree.getroot(), encoding="unicode"))
    return out


def _rename_links(root: ET.Element, names: dict[str, str]) -> None:
    for link in root.iter("link"):
        link.set("name", names.get(link.get("name"), link.get("name")))
    for joint in root.iter("joint"):
        for tag in ("parent", "child"):
            element = joint.find(tag)
            element.set("link", names.get(element.get("link"), element.get("link")))


def world_rooted(tmp_path: Path, side: str = "right") -> Path:
    """The five-finger hand under a root link ``world`` (fixed to the forearm), its forearm,
    palm and a tip named ``table``, ``object`` and ``floor``, as robot exporters and scene
    words would have them: names a simulation scene uses itself."""

    def edit(root: ET.Element) -> None:
        _rename_links(root, {"forearm": "table", "palm": "object", "lf_tip": "floor"})
        root.insert(0, ET.Element("link", name="world"))
        joint = ET.SubElement(root, "joint", name="world_to_table", type="fixed")
        ET.SubElement(joint, "parent", link="world")
        ET.SubElement(joint, "child", link="table")

    return _rewrite(hand5(tmp_path, side), tmp_path / f"world_rooted_{side}.urdf", edit)


def unbalanced_inertia(tmp_path: Path) -> Path:
    """Every link's inertia violates the triangle inequality (ixx > iyy + izz), as vendor URDFs'
    often do; MuJoCo refuses them ("inertia must satisfy A + B >= C")."""

    def edit(root: ET.Element) -> None:
        for inertia in root.iter("inertia"):
            iyy, izz = float(inertia.get("iyy")), float(inertia.get("izz"))
            inertia.set("ixx", repr(3.0 * (iyy + izz)))
            inertia.set("ixy", "0")

    return _rewrite(hand5(tmp_path), tmp_path / "unbalanced.urdf", edit)


def no_inertial(tmp_path: Path) -> Path:
    """The four-finger hand without any ``<inertial>`` (pybullet would make each link 1 kg)."""

    def edit(root: ET.Element) -> None:
        for link in root.iter("link"):
            for inertial in link.findall("inertial"):
                link.remove(inertial)

    return _rewrite(hand4(tmp_path), tmp_path / "no_inertial.urdf", edit)


def tiny_inertia(tmp_path: Path) -> Path:
    """Every link 1 mg with principal moments of 1e-9 kg m² (placeholder exporter values)."""

    def edit(root: ET.Element) -> None:
        for mass in root.iter("mass"):
            mass.set("value", "1e-6")
        for inertia in root.iter("inertia"):
            for key in ("ixx", "iyy", "izz"):
                inertia.set(key, "1e-9")
            for key in ("ixy", "ixz", "iyz"):
                inertia.set(key, "0")

    return _rewrite(hand4(tmp_path), tmp_path / "tiny_inertia.urdf", edit)


MJCF_SCENE = """
<mujoco model="scene">
  <compiler angle="radian" meshdir="assets"/>
  <include file="parts/defaults.xml"/>
  <asset><mesh name="palm_mesh" file="palm.obj"/></asset>
  <worldbody>
    <light name="top" pos="0 0 1" dir="0 0 -1"/>
    <camera name="front" pos="0.5 0 0.2" xyaxes="0 1 0 0 0 1"/>
    <geom name="floor" type="plane" size="1 1 0.1" pos="0 0 -0.3"/>
    <body name="table" pos="0.4 0 -0.2"><geom type="box" size="0.2 0.2 0.02"/></body>
    <include file="parts/hand.xml"/>
  </worldbody>
  <actuator><position name="world" joint="a1" kp="5"/></actuator>
</mujoco>
"""

MJCF_SCENE_DEFAULTS = """
<mujocoinclude>
  <default><geom rgba="0.8 0.6 0.4 1"/><joint damping="0.01"/></default>
</mujocoinclude>
"""


def mjcf_scene(tmp_path: Path) -> Path:
    """:data:`MJCF_HAND`'s gripper in a scene of its own: a light, a camera, a floor plane and a
    table in its ``<worldbody>``, the hand and its defaults in ``<include>`` files, a mesh palm
    from a mesh directory, an actuator named ``world`` (whose names MuJoCo scenes use too)."""
    folder = tmp_path / "mjcf_scene"
    (folder / "parts").mkdir(parents=True, exist_ok=True)
    (folder / "assets").mkdir(exist_ok=True)
    import trimesh

    trimesh.creation.box(extents=(0.05, 0.06, 0.04)).export(folder / "assets" / "palm.obj")
    body = MJCF_HAND.split("<worldbody>")[1].split("</worldbody>")[0]
    body = body.replace(
        '<geom type="box" size="0.03 0.03 0.025" pos="0.02 0 0.025"/>',
        '<geom type="mesh" mesh="palm_mesh" pos="0.02 0 0.025"/>',
    )
    (folder / "parts" / "hand.xml").write_text(f"<mujocoinclude>{body}</mujocoinclude>\n")
    (folder / "parts" / "defaults.xml").write_text(MJCF_SCENE_DEFAULTS)
    equality = MJCF_HAND.split("<worldbody>")[0].split('<compiler angle="radian"/>')[1]
    scene = MJCF_SCENE.replace("<worldbody>", equality + "<worldbody>", 1)
    path = folder / "scene.xml"
    path.write_text(scene)
    return path


# Every hand shaped like a public model, by name (each a function of a folder).
PUBLIC_SHAPES = {
    "world_rooted": world_rooted,
    "world_rooted_left": lambda tmp_path: world_rooted(tmp_path, "left"),
    "unbalanced_inertia": unbalanced_inertia,
    "no_inertial": no_inertial,
    "tiny_inertia": tiny_inertia,
    "mjcf_scene": mjcf_scene,
}
