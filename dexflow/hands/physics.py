"""The hand as the physics engines load it: one repaired model for MuJoCo and pybullet.

Public hand models break simulators in a few known ways. Each is repaired the way MuJoCo's
compiler offers, the same way for both engines, and said once per hand and process (logged, and
returned as one line per link by :func:`physics_urdf` and :func:`mjcf_inertials`):

- **No inertial data** (a URDF link without ``<inertial>``; an MJCF body without it and without
  geoms), or a mass or principal moment that is not positive and finite: the link gets
  ``massless_mass_kg`` at its origin with the diagonal inertia ``massless_inertia_kgm2``
  (pybullet would make it 1 kg, MuJoCo refuses a moving body without mass). This is the
  documented minimum: parameters ``simulate.massless_link_mass_kg`` (2 g) and
  ``simulate.massless_link_inertia_kgm2`` (1e-7 kg m²).
- **Principal moments that violate the triangle inequality** ``A + B >= C`` (no rigid body has
  them; vendor URDFs often do): all three are set to their mean, which is what MuJoCo's
  ``compiler balanceinertia`` does (MuJoCo refuses them otherwise; pybullet silently zeroes the
  inertia). Tiny but valid inertias (1e-9 kg m²) are kept: the engines step them stably (the
  scenes ``dexflow hand check`` builds and steps prove it for each hand).
- **A URDF root link named ``world``**: MuJoCo merges such a link into its own world body, so
  the hand would have no root to mount; the copy names it :data:`WORLD_ALIAS`.
- **URDF links listed before their parents**: pybullet (``URDF_MAINTAIN_LINK_ORDER``) computes
  NaN frames for them; the copy lists every link after its parent.
- Mesh references (``package://``, relative) become absolute paths, so the copy loads from its
  own folder.

A URDF hand needing none of these is loaded as it is. Names cannot clash with a scene's: the
MuJoCo scenes attach the hand under a prefix (:mod:`dexflow.sim.mujoco_world`), pybullet keeps each
body apart.
"""

from __future__ import annotations

import atexit
import logging
import shutil
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from dexflow.errors import HandConfigError
from dexflow.hands.files import urdf_mesh_path

if TYPE_CHECKING:
    from dexflow.hands.robot import RobotHand

__all__ = [
    "WORLD_ALIAS",
    "mjcf_inertials",
    "physics_root",
    "physics_urdf",
    "repair_inertia",
]

WORLD_ALIAS = "world_link"  # a URDF root link named 'world', renamed in the engines' copy
_BALANCE_RTOL = 1e-9  # A + B >= C within this share of C (float rounding of valid tensors)

logger = logging.getLogger(__name__)
_LOGGED: set[tuple] = set()


def repair_inertia(
    mass: float, tensor: np.ndarray, massless_mass_kg: float, massless_inertia_kgm2: float
) -> tuple[float, np.ndarray, str]:
    """A link's mass and inertia as the engines can simulate them (see the module docs).

    Args:
        mass: kg.
        tensor: (3, 3) inertia about the centre of mass, in any frame (kg m²).
        massless_mass_kg: Mass of a link without usable inertial data.
        massless_inertia_kgm2: Its principal moments.

    Returns:
        ``(mass, tensor, what)``: the mass and the (3, 3) tensor in the same frame, and what was
        changed ('' when nothing was).
    """
    tensor = np.asarray(tensor, dtype=float)
    if not np.isfinite(tensor).all() or not np.isfinite(mass):
        moments = np.full(3, np.nan)
    else:
        moments = np.linalg.eigvalsh((tensor + tensor.T) / 2)
    if not mass > 0 or not np.all(moments > 0):
        found = f"mass {mass:g} kg, principal moments {_moments(moments)}"
        default = np.eye(3) * massless_inertia_kgm2
        return (
            massless_mass_kg,
            default,
            (
                f"{found} not positive: given {massless_mass_kg:g} kg and {massless_inertia_kgm2:g} "
                "kg m²"
            ),
        )
    a, b, c = np.sort(moments)
    if a + b < c * (1 - _BALANCE_RTOL):
        mean = float(moments.mean())
        return (
            mass,
            np.eye(3) * mean,
            (
                f"principal moments {_moments(moments)} violate A + B >= C: balanced to {mean:.3g} "
                "kg m² each (MuJoCo's balanceinertia)"
            ),
        )
    return mass, tensor, ""


def _moments(values: np.ndarray) -> str:
    return "(" + ", ".join(f"{v:.3g}" for v in values) + ") kg m²"


# ---------------------------------------------------------------------------------------- URDF


def _read_inertial(link: ET.Element) -> tuple[float, np.ndarray] | None:
    """Mass and (3, 3) tensor of a URDF link's ``<inertial>`` (None without one)."""
    inertial = link.find("inertial")
    if inertial is None:
        return None
    mass_el, inertia_el = inertial.find("mass"), inertial.find("inertia")
    try:
        mass = float(mass_el.get("value")) if mass_el is not None else 0.0
        i = {k: float(inertia_el.get(k, 0.0)) for k in ("ixx", "iyy", "izz", "ixy", "ixz", "iyz")}
    except (TypeError, ValueError) as exc:
        raise HandConfigError(
            f"link '{link.get('name')}': <inertial> holds a value that is not a number: {exc}"
        ) from exc
    if inertia_el is None:
        i = dict.fromkeys(i, 0.0)
    tensor = np.array(
        [
            [i["ixx"], i["ixy"], i["ixz"]],
            [i["ixy"], i["iyy"], i["iyz"]],
            [i["ixz"], i["iyz"], i["izz"]],
        ]
    )
    return mass, tensor


def _write_inertial(link: ET.Element, mass: float, tensor: np.ndarray) -> None:
    """Replace the link's mass and inertia, keeping the ``<inertial>``'s origin (or the link
    origin where it had none)."""
    inertial = link.find("inertial")
    if inertial is None:
        inertial = ET.SubElement(link, "inertial")
        ET.SubElement(inertial, "origin", xyz="0 0 0", rpy="0 0 0")
    for tag in ("mass", "inertia"):
        for old in inertial.findall(tag):
            inertial.remove(old)
    ET.SubElement(inertial, "mass", value=f"{mass:.9g}")
    keys = {
        "ixx": (0, 0),
        "iyy": (1, 1),
        "izz": (2, 2),
        "ixy": (0, 1),
        "ixz": (0, 2),
        "iyz": (1, 2),
    }
    ET.SubElement(inertial, "inertia", {k: f"{tensor[i, j]:.9g}" for k, (i, j) in keys.items()})


def _parents_first(root: ET.Element) -> list[ET.Element]:
    """The URDF's links, each after its parent (the order pybullet needs)."""
    links = {link.get("name"): link for link in root.findall("link")}
    children: dict[str, list[str]] = {}
    has_parent = set()
    for joint in root.findall("joint"):
        parent, child = joint.find("parent"), joint.find("child")
        if parent is None or child is None:
            continue
        children.setdefault(parent.get("link"), []).append(child.get("link"))
        has_parent.add(child.get("link"))
    order: list[str] = []
    stack = [n for n in links if n not in has_parent][::-1]
    while stack:
        name = stack.pop()
        if name in links and name not in order:
            order.append(name)
            stack.extend(reversed(children.get(name, [])))
    order += [n for n in links if n not in order]  # unreachable links keep their place, last
    return [links[n] for n in order]


def _repair_urdf(
    source: Path, massless_mass_kg: float, massless_inertia_kgm2: float
) -> tuple[ET.ElementTree, list[str]]:
    """The URDF's tree with every repair applied (and mesh paths made absolute), and what was
    repaired: nothing means the engines can load the file as it is."""
    try:
        tree = ET.parse(source)
    except (OSError, ET.ParseError) as exc:
        raise HandConfigError(f"{source}: cannot read the URDF: {exc}") from exc
    root = tree.getroot()
    notes = []
    for link in root.findall("link"):
        name = link.get("name")
        found = _read_inertial(link)
        if found is None:
            mass, tensor = massless_mass_kg, np.eye(3) * massless_inertia_kgm2
            what = (
                f"no <inertial>: given {massless_mass_kg:g} kg and {massless_inertia_kgm2:g} kg m²"
            )
        else:
            mass, tensor, what = repair_inertia(*found, massless_mass_kg, massless_inertia_kgm2)
        if what:
            _write_inertial(link, mass, tensor)
            notes.append(f"link '{name}': {what}")
    ordered = _parents_first(root)
    reordered = [link.get("name") for link in ordered] != [
        link.get("name") for link in root.findall("link")
    ]
    if reordered:
        for link in ordered:
            root.remove(link)
        for k, link in enumerate(ordered):
            root.insert(k, link)
        notes.append("links listed after their parents (pybullet computes NaN frames otherwise)")
    if ordered and ordered[0].get("name") == "world":
        _rename_link(root, "world", WORLD_ALIAS)
        notes.append(
            f"root link 'world' named '{WORLD_ALIAS}' (MuJoCo merges 'world' into its own)"
        )
    for mesh in root.iter("mesh"):
        if mesh.get("filename"):
            try:
                path = urdf_mesh_path(mesh.get("filename"), source.parent)
            except HandConfigError:  # an unresolvable package:// mesh stays as it was
                continue
            if path.is_file():  # (collision meshes are checked when the hand is loaded)
                mesh.set("filename", str(path.resolve()))
    return tree, notes


def _rename_link(root: ET.Element, old: str, new: str) -> None:
    for link in root.findall("link"):
        if link.get("name") == old:
            link.set("name", new)
    for joint in root.findall("joint"):
        for tag in ("parent", "child"):
            element = joint.find(tag)
            if element is not None and element.get("link") == old:
                element.set("link", new)


def physics_urdf(
    hand: RobotHand, massless_mass_kg: float, massless_inertia_kgm2: float
) -> tuple[Path, list[str]]:
    """The URDF that pybullet (and, for URDF hands, MuJoCo) loads for ``hand``.

    A URDF hand needing no repair is its own file. Otherwise a repaired copy, and for an MJCF
    hand its export (:func:`dexflow.hands.export.export_urdf`: MuJoCo's masses and inertias,
    repaired alike), is written once per process to a temporary folder.

    Args:
        hand: The hand.
        massless_mass_kg: Mass given to links without usable inertial data (> 0).
        massless_inertia_kgm2: Their principal moments (> 0).

    Returns:
        The URDF's path and one line per repair (empty for a model loaded as it is).

    Raises:
        HandConfigError: The model cannot be read or the defaults are not positive.
    """
    if not massless_mass_kg > 0 or not massless_inertia_kgm2 > 0:
        raise HandConfigError(
            f"default link inertial data must be positive: mass {massless_mass_kg!r} kg, "
            f"inertia {massless_inertia_kgm2!r} kg·m²"
        )
    source = Path(hand.model.path)
    key = (str(source), source.stat().st_mtime_ns, hand.model.root, massless_mass_kg,
           massless_inertia_kgm2)  # fmt: skip
    if key not in _URDF_CACHE:
        folder = Path(tempfile.mkdtemp(prefix="dexflow-urdf-"))
        atexit.register(shutil.rmtree, folder, ignore_errors=True)
        out = folder / f"{hand.spec.name}.urdf"
        model = source
        if hand.model.format == "mjcf":
            from dexflow.hands.export import export_urdf

            model = export_urdf(hand.model, folder / f"{hand.spec.name}_export.urdf")
        tree, notes = _repair_urdf(model, massless_mass_kg, massless_inertia_kgm2)
        if notes or model != source:
            ET.indent(tree)
            text = ET.tostring(tree.getroot(), encoding="unicode")
            header = (
                f'<?xml version="1.0"?>\n<!-- {source.name} as the physics engines load it, '
                f"written by dexflow: {len(notes)} repair(s), see dexflow.hands.physics. -->\n"
            )
            out.write_text(header + text + "\n", encoding="utf-8")
        else:
            out = source
        _URDF_CACHE[key] = (out, notes)
    out, notes = _URDF_CACHE[key]
    _log_once(hand, notes)
    return out, list(notes)


_URDF_CACHE: dict[tuple, tuple[Path, list[str]]] = {}


def physics_root(hand: RobotHand) -> str:
    """The hand's root link as named in :func:`physics_urdf`'s file (URDF) or the MJCF."""
    root = hand.model.root
    return WORLD_ALIAS if hand.model.format == "urdf" and root == "world" else root


# ---------------------------------------------------------------------------------------- MJCF


def mjcf_inertials(
    hand: RobotHand, massless_mass_kg: float, massless_inertia_kgm2: float
) -> tuple[dict[str, tuple[float, np.ndarray, np.ndarray, np.ndarray]], list[str]]:
    """The repaired inertial data of an MJCF hand's bodies, from MuJoCo's own compilation.

    Returns:
        Per body that needs it ``(mass, ipos (3,), iquat (4,) w-x-y-z, diaginertia (3,))`` to
        set explicitly in the scene, and one line per repair.
    """
    m = hand.model.mj_model
    names = {m.body(i).name: i for i in range(m.nbody)}
    root_id = names[hand.model.root]
    subtree = {root_id}
    for b in range(root_id + 1, m.nbody):  # bodies come after their parents
        if int(m.body_parentid[b]) in subtree:
            subtree.add(b)
    out, notes = {}, []
    for b in sorted(subtree):
        name = m.body(b).name
        mass, moments = float(m.body_mass[b]), np.asarray(m.body_inertia[b], dtype=float)
        if mass == 0 and not (m.geom_bodyid == b).any():
            new_mass, tensor = massless_mass_kg, np.eye(3) * massless_inertia_kgm2
            what = f"no inertial data: given {massless_mass_kg:g} kg and {massless_inertia_kgm2:g} kg m²"
            ipos, iquat = np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0])
        else:
            new_mass, tensor, what = repair_inertia(
                mass, np.diag(moments), massless_mass_kg, massless_inertia_kgm2
            )
            ipos, iquat = np.array(m.body_ipos[b]), np.array(m.body_iquat[b])
        if what:
            out[name] = (new_mass, ipos, iquat, np.diag(tensor).copy())
            notes.append(f"body '{name}': {what}")
    _log_once(hand, notes)
    return out, notes


def _log_once(hand: RobotHand, notes: list[str]) -> None:
    key = (hand.spec.name, str(hand.model.path), tuple(notes))
    if notes and key not in _LOGGED:
        _LOGGED.add(key)
        logger.info(
            "hand '%s': the physics engines load %s with %d repair(s):\n  %s",
            hand.spec.name, Path(hand.model.path).name, len(notes), "\n  ".join(notes),
        )  # fmt: skip
