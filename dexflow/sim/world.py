"""The interface of a physics engine's grasp world, and the one place an engine is chosen.

Stage simulate runs the paper's grasp test (and MuJoCo also DexGraspBench's) through any
:class:`GraspWorld`; stage replay plays trajectories back in MuJoCo's
(:class:`dexflow.sim.mujoco_world.MujocoGraspWorld`, whose scene it extends with a driven base,
gravity and a table). An engine is added by implementing this protocol and naming it in
:data:`dexflow.params.ENGINES`; ``simulate.engines`` then accepts it.

A world is built once per process, engine and hand (:func:`grasp_world`): loading and checking
a hand model costs far more than a test, and every test starts from a freshly reset state, so a
frame's result never depends on the frames tested before it.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Protocol

import numpy as np

from dexflow.params import ENGINES

if TYPE_CHECKING:
    from dexflow.hands.robot import RobotHand
    from dexflow.params import SimulateParams
    from dexflow.sim.protocol import Perturbation

__all__ = ["ENGINES", "GraspWorld", "grasp_world"]


class GraspWorld(Protocol):
    """A hand and an object in one engine, tested one frame at a time."""

    hand: RobotHand
    params: SimulateParams

    def set_object(self, convex_obj: str | Path) -> None:
        """Load the object from its convex parts (one ``.obj``, stage scale_align's)."""

    def gap(self, q: np.ndarray, pose: np.ndarray, links: list[str] | None = None) -> float:
        """Signed distance (m) between the hand at ``q`` and the object at ``pose`` in the
        engine's collision geometry (negative: the deepest overlap)."""

    def test_frame(
        self, q: np.ndarray, pose: np.ndarray, perturbation: Perturbation | None = None
    ) -> dict:
        """The six-direction test of one frame (stage simulate's protocol); its per-test
        results (held, displacement, rotation) and the frame's diagnostics."""

    def close(self) -> None:
        """Release the engine's resources."""


_WORLDS: dict[tuple[str, int], GraspWorld] = {}


def grasp_world(engine: str, hand: RobotHand, params: SimulateParams) -> GraspWorld:
    """The world of ``engine`` (one of :data:`ENGINES`) for ``hand``: one per process, engine
    and hand, rebuilt when ``params`` change.

    Raises:
        ValueError: ``engine`` is none of :data:`ENGINES`.
    """
    if engine not in ENGINES:
        raise ValueError(f"unknown physics engine {engine!r}; expected one of {list(ENGINES)}")
    key = (engine, id(hand))
    world = _WORLDS.get(key)
    if world is None or world.params != params:
        if engine == "mujoco":
            from dexflow.sim.mujoco_world import MujocoGraspWorld

            world = MujocoGraspWorld(hand, params)
        else:
            from dexflow.sim.pybullet_world import PybulletGraspWorld, hand_urdf

            world = PybulletGraspWorld(hand, hand_urdf(hand, params), params)
        _WORLDS[key] = world
    return world
