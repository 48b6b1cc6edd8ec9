"""Stage track's search: the targets that make the replay carry the object.

A refined trajectory is kinematic: played back with the object free (stage replay), the fingers
merely touch it, so they press next to nothing, and the object is shoved off or left behind.
:func:`track_sequence` searches, in the replay's own MuJoCo scene
(:class:`~dexflow.sim.replay_world.ReplayWorld`: the same base servos, finger actuators, table
and gravity), for the position targets under which the object follows its recorded path. Two
steps, each scored in the physics:

1. **Grip schedule** (contact guidance). Where stage contact has a finger on the object, the
   hand links within ``squeeze_reach_m`` of it are pushed ``squeeze_m`` into it at its recorded
   pose (a position servo presses only as hard as its target lies inside) and, before the
   grasp, pulled as far out (stage simulate's pregrasp and squeeze configurations,
   :func:`dexflow.sim.grip.grip_parts`). A schedule ``(scale, ramp, lead, backoff, hold)``
   closes the fingers with ``scale`` times that push, ramped in over ``ramp`` frames ending
   ``lead`` frames before the **lift** (the first frame after the first contact where the
   recorded object is 1 cm from where it was then: fingers closing on an object at rest shove
   it), holds them ``backoff`` times the pull back from the object until then and, from the
   lift on, by ``hold`` (:func:`dexflow.sim.grip.guided_targets`): lets the targets follow the
   refined trajectory (``follow``), keeps the fingers' targets as they are at the lift
   (``fingers``: the grasp held as formed) or keeps them so and moves the base with the human
   fingertips' rigid motion (``grasp``: the grasp carried as one body,
   :func:`dexflow.sim.carry.grasp_carry`). A refined
   trajectory's fingers keep moving against the recorded object while it is carried, because
   the recorded object turns against the hand (annotation jitter of a tenth of a radian per
   frame, and real regrasps): on the real captures the fingers open and close by up to 2-4 cm
   mid-carry, and a grasp that follows them lets go. Held fingers on the refined base miss the
   human's fingertips by centimetres (the wrist turns under the grasp); carried as one body
   they would miss them by millimetres, but the hand then moves as fast as the human's
   fingertips, whose lift accelerates to 0.5-0.8 m/s within a frame or two, and the simulated
   grip flings or drops the object there unless the motion is smoothed over several frames
   (``carry_smooth_frames``; with 8, two more captures of 28 carried, with either hand, at
   1-4 mm more fingertip error): off by default (measured in docs/method.md). Every
   schedule of the grid ``schedule_scales x schedule_ramps x schedule_leads x
   schedule_backoffs x schedule_holds`` is replayed whole. The search starts from the best by
   success, then carried, then the error below (a schedule that carries the object is the
   likeliest start to reach success); the best by :func:`replay_rank` (success, then the
   error) is the fallback output.
2. **Receding horizon** (``mpc``). At frame ``t`` of the replay window the simulation state is
   saved; candidate targets for frames ``t+1 .. t+horizon_frames`` are each rolled out from it
   (``substeps`` physics steps per frame, exactly as the replay steps); the cheapest becomes the
   plan, its first frame is applied, and the search moves on to ``t+1`` with the rest of the
   plan as its start. ``iterations`` rounds per frame, each around the best so far with its
   spread halved. Candidates: the plan so far; the prior (the refined trajectory, hinges
   unwrapped); the plan with the fingers pressed half as much and half again as much; with
   ``object_guidance`` the plan with the base shifted by the object's position error now (a
   held object follows the hand), by all of it and by half; and ``samples`` random
   perturbations of the plan: per candidate two offsets, for the first and the last frame of
   the horizon, linear between, normal with spreads ``noise_base_m`` (base translation),
   ``noise_base_rad`` (base rotation), ``noise_finger_rad`` (finger joints), plus each finger's
   push scaled by a normal share. Cost of a rollout, averaged over its frames: the object's
   position error plus ``rotation_weight_m_per_rad`` times its rotation error (against the
   recorded pose; before the first contact, the pose there: it rests), ``contact_weight`` times
   the share of stage contact's fingers that do not touch it in the simulation,
   ``prior_weight`` times the targets' distance from the grip schedule's (base translation in
   m, base rotation and the fingers' mean in rad times 0.1 and 0.05 m/rad: about how far a
   fingertip moves), and ``tip_weight`` times the mean distance (m) of the simulated hand's
   fingertips from the refined trajectory's (:func:`dexflow.measures.fingertips`: the
   keypoints the fingertip error measures). The search's result is kept only where its replay
   ranks at least as high as the fallback schedule's; else that schedule is the output.

**Ranking** a replay (the grid's schedules, the search's result, :func:`replay_rank`): success
first, then the mean object error (position plus ``rotation_weight_m_per_rad`` times rotation)
plus ``tip_weight`` times the simulated fingertips' mean distance from the refined trajectory's
over the window. Without the fingertip term the search kept whichever of equally successful
targets tracked the object best, wherever the hand went: pressed fingers that bent round the
object, a base dragged by it; the tracked hand's fingertips were 22 / 18 mm (Shadow / Allegro,
28 real DexYCB captures) from the human's against the refined trajectory's 4.6 / 5.2. With
``tip_weight`` 20 (a centimetre of fingertip distance costs as much as 20 cm of object error,
so among equals the fingertips decide) they are 9 / 9 mm, with as many successes.
"Carried" (the replay's criterion that the object ends nearer its recording than left behind)
ranks only the search's start (before the error: a schedule that carries the object is the
likeliest start to reach success), not the output. Ranking the output, among failures it
preferred a replay that drags the object along with fingers curled 5-6 cm from the human's
over one that stays on the refined fingertips and drops it; neither is usable, and the second
is the better record of the human's motion. There it cost Shadow 1.2 mm of mean fingertip
error on those captures (two failures at 36 and 19 mm instead of 10 and 12), for two more
objects carried and no more successes (docs/method.md has the measurements).

What measured what, on the demo (Shadow, 24 sequences): the refined trajectory carries 8 %
(success); one schedule 38 %; the grid of 48 alone 46 %; the grid and the receding horizon
50 % (13 CPU s per 70 frames). Moving the base by the object's error as feedback at every frame
jerks the hand (its velocity is fed forward to the servos): one schedule with it, 38 % -> 4 %.
With the demo's misread-rotation artefacts on (tilted rests, spinning annotations): refine 4 %,
the whole search 25 %. On 28 real DexYCB captures, holding the grasp from the lift (the grid
with and without it) took the whole search from 39 to 50 % (Shadow) and from 14 to 36 %
(Allegro); pressing the fingers with balanced forces instead of equal depths, stronger presses
(up to 8x) or a wider reach did not change the Allegro rate by more than one sequence.

The tracked trajectory's ``q`` is the state the hand reaches in the simulation (where it really
is: fingers stopped at the object's surface, the base where its force-limited servos got it);
``targets`` are the position targets that reach it, the controls a robot would be given.
Outside the replay window both are the prior. A replay of ``targets`` (stage replay does so
whenever a trajectory has them) reproduces the search's final rollout exactly: the same scene,
steps and state.

**Feasible** means the final rollout succeeds by the replay's own criteria (SPIDER's thresholds
and carried, :func:`dexflow.sim.replay_criteria.sequence_result`); an object no hand motion near
the prior can carry (out of reach, too heavy for the servos) is reported not feasible, its best
attempt kept for inspection, never a success.

Deterministic: the random perturbations come from the generator the caller seeds (stage track:
the pipeline seed and the sequence's name), MuJoCo steps single-threaded from a reset state.
"""

from __future__ import annotations

import itertools

import numpy as np

from dexflow.measures import fingertips
from dexflow.params import TrackParams
from dexflow.sim.carry import grasp_carry
from dexflow.sim.grip import grip_parts, guided_targets
from dexflow.sim.replay_criteria import replay_errors, sequence_result
from dexflow.sim.replay_world import ReplayWorld

__all__ = ["replay_rank", "track_sequence"]

_BASE_ROT_LEVER_M = 0.1  # m/rad: the prior cost of a base rotation (palm to fingertip)
_FINGER_LEVER_M = 0.05  # m/rad: the prior cost of a finger joint's rotation (a phalanx)


def _finger_of_body(world: ReplayWorld) -> np.ndarray:
    """(nbody,) the index of the finger (``hand.spec.fingers`` order) each body belongs to, -1
    for bodies of no finger."""
    from dexflow.sim.mujoco_world import hand_name

    m = world.model
    out = np.full(m.nbody, -1)
    names = {m.body(i).name: i for i in range(m.nbody)}
    for f, finger in enumerate(world.hand.spec.fingers.values()):
        for link in finger.links:
            body = names.get(hand_name(link))
            if body is not None:
                out[body] = f
    return out


class _Rollouts:
    """Rollouts of candidate targets from one saved state, and their costs."""

    def __init__(
        self,
        world: ReplayWorld,
        prior: np.ndarray,
        poses: np.ndarray,
        fps: float,
        first: int,
        fingers: np.ndarray,
        settings: TrackParams,
        tips: np.ndarray | None,
    ) -> None:
        self.world, self.prior, self.fps, self.s = world, prior, fps, settings
        self.tips = tips
        self.goal = poses.copy()
        self.goal[:first] = poses[first]  # before the first contact the object rests there
        self.fingers = np.asarray(fingers, dtype=bool)  # (T, F) stage contact's fingers
        self.finger_of_body = _finger_of_body(world)
        self.object_body = world._object
        n = len(world.hand.spec.fingers)
        self._touch = np.zeros(n, dtype=bool)
        self.lever = np.concatenate(
            [np.ones(3), np.full(3, _BASE_ROT_LEVER_M), np.full(prior.shape[1] - 6, 1.0)]
        )

    def touching(self) -> np.ndarray:
        """(F,) fingers touching the object in the simulation now."""
        m, d = self.world.model, self.world.data
        touch = self._touch
        touch[:] = False
        n = d.ncon
        if n:
            bodies = m.geom_bodyid[d.contact.geom[:n]]  # (C, 2)
            other = np.where(bodies[:, 0] == self.object_body, bodies[:, 1], bodies[:, 0])
            with_object = (bodies == self.object_body).any(axis=1)
            finger = self.finger_of_body[other[with_object]]
            touch[finger[finger >= 0]] = True
        return touch.copy()

    def run(
        self, start_target: np.ndarray, plan: np.ndarray, frames: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Roll ``plan (K, dof)`` (targets of ``frames``) out from the current state, starting
        from ``start_target`` (the targets of the frame before); returns the object's poses
        (K, 7), the share of stage contact's fingers missing (K,) and the hand's states
        (K, dof) at each frame."""
        world, fps = self.world, self.fps
        objects = np.empty((len(frames), 7))
        states = np.empty((len(frames), plan.shape[1]))
        missing = np.zeros(len(frames))
        previous = start_target
        for k, t in enumerate(frames):
            world.advance(previous, plan[k], fps)
            previous = plan[k]
            objects[k], states[k] = world.object_pose7(), world.hand_state()
            wanted = self.fingers[t]
            if wanted.any():
                missing[k] = (wanted & ~self.touching()).sum() / wanted.sum()
        return objects, missing, states

    def costs(self, plans: np.ndarray, frames: np.ndarray, rolled: list[tuple]) -> np.ndarray:
        """(N,) the costs of ``plans (N, K, dof)`` whose rollouts gave ``rolled`` (:meth:`run`'s
        outputs, one per plan)."""
        s = self.s
        objects, missing, states = (np.array(x) for x in zip(*rolled, strict=True))
        position, rotation = replay_errors(
            objects[..., :3].reshape(-1, 3), objects[..., 3:].reshape(-1, 4),
            np.broadcast_to(self.goal[frames], (len(plans), len(frames), 4, 4)).reshape(-1, 4, 4),
        )  # fmt: skip
        tracking = (position + s.rotation_weight_m_per_rad * rotation).reshape(len(plans), -1)
        deviation = np.abs(plans - self.prior[frames]) * self.lever
        prior = (
            np.linalg.norm(deviation[..., :3], axis=-1)
            + np.linalg.norm(deviation[..., 3:6], axis=-1)
            + _FINGER_LEVER_M * deviation[..., 6:].mean(axis=-1)
        )
        total = tracking.mean(axis=1) + s.contact_weight * missing.mean(axis=1)
        total += s.prior_weight * prior.mean(axis=1)
        if s.tip_weight:
            total += s.tip_weight * _tip_distance(self.world.hand, states, self.tips[frames])
        return total


def _tip_distance(hand, states: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """(N,) the mean distance (m) of the fingertips of ``states (N, K, dof)`` from ``goal
    (K, F, 3)`` over the fingertips and the K frames."""
    return np.linalg.norm(fingertips(hand, states) - goal, axis=-1).mean(axis=(-1, -2))


def _noise(
    rng: np.random.Generator, count: int, length: int, dof: int, s: TrackParams, scale: float
) -> np.ndarray:
    """(count, length, dof) perturbations: normal offsets at the horizon's first and last frame,
    linear between."""
    spread = np.concatenate(
        [np.full(3, s.noise_base_m), np.full(3, s.noise_base_rad),
         np.full(dof - 6, s.noise_finger_rad)]
    ) * scale  # fmt: skip
    ends = rng.standard_normal((count, 2, dof)) * spread
    ramp = np.linspace(0.0, 1.0, length)[None, :, None] if length > 1 else np.ones((1, 1, 1))
    return ends[:, :1] + ramp * (ends[:, 1:] - ends[:, :1])


def replay_rank(result: dict, tip_distance_m: float, s: TrackParams) -> tuple[bool, float]:
    """The rank of a replay (lower is better; module docs): successes before failures, then the mean
    object pose error (``result``: :func:`~dexflow.sim.replay_criteria.sequence_result`'s
    entry) plus ``tip_weight`` times ``tip_distance_m``, the simulated fingertips' mean distance
    from the refined trajectory's."""
    error = result["position_error_mean_m"]
    error += s.rotation_weight_m_per_rad * result["rotation_error_mean_rad"]
    return not result["success"], error + s.tip_weight * tip_distance_m


def _replay_rank(
    world: ReplayWorld,
    targets: np.ndarray,
    poses: np.ndarray,
    fps: float,
    window: tuple[int, int, int],
    s: TrackParams,
    tips: np.ndarray | None,
) -> tuple[tuple[bool, float], dict]:
    """:func:`replay_rank` of a replay of ``targets`` (``tips (T, F, 3)``: the refined
    trajectory's fingertips) and the replay's summary entry
    (:func:`~dexflow.sim.replay_criteria.sequence_result`)."""
    rows = world.replay(targets, poses, fps, window)
    r = sequence_result(rows, window[1], poses, fps, world.replay_params)
    distance = 0.0
    if s.tip_weight:
        frames = rows["frame"]
        distance = _tip_distance(world.hand, rows["hand_q"][None], tips[frames])[0]
    return replay_rank(r, distance, s), r


def _per_finger(push: np.ndarray, hand) -> np.ndarray:
    """(F, T, dof) ``push (T, dof)`` split by finger: each finger's joints' columns only."""
    names = list(hand.joint_names)
    out = np.zeros((len(hand.spec.fingers), *push.shape))
    for f, finger in enumerate(hand.spec.fingers.values()):
        columns = [names.index(j) for j in finger.joints if j in names]
        out[f][:, columns] = push[:, columns]
    return out


def track_sequence(
    world: ReplayWorld,
    q: np.ndarray,
    poses: np.ndarray,
    fps: float,
    window: tuple[int, int, int],
    fingers: np.ndarray,
    settings: TrackParams,
    rng: np.random.Generator,
    clamp=None,
    tips: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """Search the targets under which the replay carries the object (module docs).

    Args:
        world: The replay's scene with the sequence's object set; its ``squeeze_m`` is the
            contact guidance's push (:meth:`ReplayWorld.squeezed`).
        q: (T, dof) the prior (the refined trajectory).
        poses: (T, 4, 4) the recorded object poses.
        fps: Frames per second.
        window: ``(start, first_contact, end)``: the replay's window
            (:func:`dexflow.sim.replay_criteria.replay_window`).
        fingers: (T, F) stage contact's final states (which fingers touch the object).
        settings: The search's settings.
        rng: The random generator of the perturbations.
        clamp: Maps (N, dof) targets into the hand's joint limits and couplings (None: as
            they are).
        tips: (T, K, 3) the human fingertips (NaN where not observed), for the schedules
            that carry the grasp as one body (``hold`` ``"grasp"``; needed only for those).

    Returns:
        ``q`` (T, dof) the simulated hand's states in the window (the prior elsewhere),
        ``targets`` (T, dof), ``object_pose7`` (T, 7) the simulated object in the window (NaN
        elsewhere), ``cost`` (T,) of the chosen plan at each frame (NaN outside the window and
        where the output is a grip schedule) and ``replayed``, the replay's summary entry for
        ``targets`` (:func:`~dexflow.sim.replay_criteria.sequence_result`).
    """
    s = settings
    prior = np.array(q, dtype=float)
    prior[:, 3:6] = np.unwrap(prior[:, 3:6], axis=0)
    poses = np.asarray(poses, dtype=float)
    parts = grip_parts(world, prior, poses, window, fingers, s)
    goal_tips = fingertips(world.hand, prior) if s.tip_weight else None
    carried = None
    if "grasp" in s.schedule_holds:
        if tips is None:
            raise ValueError("hold 'grasp' needs the human fingertips (tips)")
        carried = grasp_carry(prior[:, :6], tips, poses, window, s.carry_smooth_frames)
    grid = itertools.product(
        s.schedule_scales, s.schedule_ramps, s.schedule_leads, s.schedule_backoffs,
        s.schedule_holds,
    )  # fmt: skip
    best_rank, best, replayed = None, prior, {}  # the output's ranking (replay_rank)
    start_rank, guided = None, prior  # the search's start: carried before the error
    for schedule in grid:
        targets = guided_targets(prior, parts, poses, window, schedule, carried)
        rank, result = _replay_rank(world, targets, poses, fps, window, s, goal_tips)
        start = (rank[0], not result["carried"], rank[1])
        if best_rank is None or rank < best_rank:  # the first of equals: deterministic
            best_rank, best, replayed = rank, targets, result
        if start_rank is None or start < start_rank:
            start_rank, guided = start, targets
    if s.mpc:
        out = _search(
            world, prior, guided, parts[0], poses, fps, window, fingers, s, rng, clamp, goal_tips
        )  # fmt: skip
        rank, result = _replay_rank(world, out["targets"], poses, fps, window, s, goal_tips)
        if rank <= best_rank:
            return {**out, "replayed": result}
    return {**_play(world, prior, best, poses, fps, window), "replayed": replayed}


def _play(
    world: ReplayWorld,
    prior: np.ndarray,
    targets: np.ndarray,
    poses: np.ndarray,
    fps: float,
    window: tuple[int, int, int],
) -> dict[str, np.ndarray]:
    """:func:`track_sequence`'s outputs for ``targets`` played as they are."""
    start, _, end = window
    states = prior.copy()
    objects = np.full((len(prior), 7), np.nan)
    world.begin(targets, poses, fps, window)
    states[start], objects[start] = targets[start], world.object_pose7()
    for t in range(start, end):
        world.advance(targets[t], targets[t + 1], fps)
        states[t + 1], objects[t + 1] = world.hand_state(), world.object_pose7()
    cost = np.full(len(prior), np.nan)
    return {"q": states, "targets": targets, "object_pose7": objects, "cost": cost}


def _search(
    world: ReplayWorld,
    prior: np.ndarray,
    guided: np.ndarray,
    full: np.ndarray,
    poses: np.ndarray,
    fps: float,
    window: tuple[int, int, int],
    fingers: np.ndarray,
    s: TrackParams,
    rng: np.random.Generator,
    clamp,
    tips: np.ndarray | None,
) -> dict[str, np.ndarray]:
    """The receding-horizon search around the grip schedule ``guided`` (module docs); returns
    :func:`track_sequence`'s outputs."""
    start, first, end = window
    squeeze = _per_finger(full, world.hand)  # (F, T, dof)
    rollouts = _Rollouts(world, guided, poses, fps, first, fingers, s, tips)
    clamp = clamp or (lambda x: x)
    plan = guided.copy()
    states = prior.copy()
    objects = np.full((len(prior), 7), np.nan)
    costs = np.full(len(prior), np.nan)
    world.begin(plan, poses, fps, window)
    objects[start] = world.object_pose7()
    if start < end:  # the replay's start velocity is the targets' there: the schedule's, kept
        world.advance(plan[start], plan[start + 1], fps)
        states[start + 1] = world.hand_state()
        objects[start + 1] = world.object_pose7()
    dof = prior.shape[1]
    for t in range(start + 1, end):
        frames = np.arange(t + 1, min(t + s.horizon_frames, end) + 1)
        saved = world._state()
        fixed = [plan[frames], prior[frames]]
        if s.squeeze_m > 0:
            fixed += [plan[frames] + k * full[frames] for k in (-0.5, 0.5)]
        if s.object_guidance:
            error = poses[max(t, first), :3, 3] - objects[t, :3]
            for share in (0.5, 1.0):
                moved = plan[frames].copy()
                moved[:, :3] += share * error
                fixed.append(moved)
        best_cost, best = np.inf, plan[frames]
        candidates = np.array(fixed)
        for round_ in range(s.iterations):
            if round_ > 0 or s.samples:
                noise = _noise(rng, s.samples, len(frames), dof, s, 0.5**round_)
                if s.squeeze_m > 0:  # contact guidance: each finger pressed more or less
                    shares = rng.normal(0.0, 0.5**round_, (s.samples, len(squeeze)))
                    noise += np.einsum("nf,fkd->nkd", shares, squeeze[:, frames])
                sampled = best[None] + noise
                candidates = sampled if round_ else np.concatenate([candidates, sampled])
            candidates = clamp(candidates.reshape(-1, dof)).reshape(candidates.shape)
            rolled = []
            for candidate in candidates:
                world._restore(saved)
                rolled.append(rollouts.run(plan[t], candidate, frames))
            costs_now = rollouts.costs(candidates, frames, rolled)
            pick = int(np.argmin(costs_now))  # the first of equals: deterministic
            if costs_now[pick] < best_cost:
                best_cost, best = float(costs_now[pick]), candidates[pick]
        plan[frames] = best
        costs[t + 1] = best_cost
        world._restore(saved)
        world.advance(plan[t], plan[t + 1], fps)
        states[t + 1] = world.hand_state()
        objects[t + 1] = world.object_pose7()
    states[start] = plan[start]
    return {"q": states, "targets": plan, "object_pose7": objects, "cost": costs}
