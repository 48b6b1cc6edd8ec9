"""Stage track's grip schedules (contact guidance): the targets that close the fingers on the
object before the lift and hold them while it is carried.

:func:`grip_parts` finds the two moves of the fingers (pressed into the object at its recorded
pose, pulled as far out), :func:`grip_schedule` when the press ramps in, and
:func:`guided_targets` combines them into a schedule's targets, with the hold from the lift on.
:func:`dexflow.sim.track.track_sequence` replays every schedule of the grid and starts its
search from the best (its module docs say why each part is there).
"""

from __future__ import annotations

import numpy as np

from dexflow.params import TRACK_HOLDS, TrackParams
from dexflow.sim.replay_criteria import lift_frame
from dexflow.sim.replay_world import ReplayWorld

__all__ = ["grip_parts", "grip_schedule", "guided_targets"]


def grip_schedule(
    poses: np.ndarray, window: tuple[int, int, int], ramp: int, lead: int = 0
) -> np.ndarray:
    """(T,) how much of the squeeze the contact guidance applies at each frame: 0 until ``ramp``
    frames before ``lead`` frames before the lift (fingers closing on an object at rest shove
    it), 1 from there to the window's end, linear between."""
    end = window[2]
    done = lift_frame(poses, window) - lead
    share = np.clip((np.arange(len(poses)) - (done - ramp)) / max(ramp, 1), 0.0, 1.0)
    share[end + 1 :] = 0.0
    return share


def grip_parts(
    world: ReplayWorld,
    prior: np.ndarray,
    poses: np.ndarray,
    window: tuple[int, int, int],
    fingers: np.ndarray,
    s: TrackParams,
) -> tuple[np.ndarray, np.ndarray]:
    """The contact guidance's two moves of the fingers, (T, dof) each: ``squeeze - prior``, the
    links within ``squeeze_reach_m`` pushed ``squeeze_m`` into the object at its recorded pose
    (frames where stage contact has a finger on it, 0 elsewhere), and ``release - prior``, them
    pulled as far out (stage simulate's pregrasp)."""
    start, first, end = window
    touching = np.asarray(fingers, dtype=bool).any(axis=1)
    full = np.zeros_like(prior)
    release = np.zeros_like(prior)
    if s.squeeze_m > 0:
        for t in range(start, end + 1):
            configs = world.targets(prior[t], poses[max(t, first)])[0]
            if touching[t]:
                full[t] = configs["squeeze"] - prior[t]
            release[t] = configs["pregrasp"] - prior[t]
    return full, release


def guided_targets(
    prior: np.ndarray,
    parts: tuple[np.ndarray, np.ndarray],
    poses: np.ndarray,
    window: tuple[int, int, int],
    schedule: tuple[float, int, int, float, str],
    carried: np.ndarray | None = None,
) -> np.ndarray:
    """(T, dof) the contact-guided prior: fingers backed off during the approach, closed
    together into the object at the grasp, and (``hold``) kept so while it is carried.

    With ``schedule = (scale, ramp, lead, backoff, hold)``, ``a(t)`` the grip schedule
    (:func:`grip_schedule` of ``ramp`` and ``lead``) and ``(squeeze, release)`` the ``parts``
    (:func:`grip_parts`), the targets are ``prior + scale a squeeze + b release``,
    ``b(t) = backoff (1 - a(t))`` before the lift, 0 from it. From the lift to the window's
    end, by ``hold``: ``"follow"`` leaves them so; ``"fingers"`` keeps the finger targets (not
    the base's) as they are at the lift; ``"grasp"`` keeps them so and takes the base's from
    ``carried (T, 6)`` (:func:`dexflow.sim.carry.grasp_carry`: the grasp moved as one body).
    """
    full, release = parts
    scale, ramp, lead, backoff, hold = schedule
    if hold not in TRACK_HOLDS:
        raise ValueError(f"hold {hold!r}: expected one of {TRACK_HOLDS}")
    share = grip_schedule(poses, window, int(ramp), int(lead))
    back = backoff * (1.0 - share)
    lift = lift_frame(poses, window)
    back[lift:] = 0.0
    out = prior + scale * share[:, None] * full + back[:, None] * release
    carry = slice(lift, window[2] + 1)
    if hold != "follow":
        out[carry, 6:] = out[lift, 6:]
    if hold == "grasp":
        if carried is None:
            raise ValueError("hold 'grasp' needs the carried base (grasp_carry)")
        out[carry, :6] = carried[carry]
    return out
