"""Stage retarget (paper §III-B): human keypoints -> robot joint trajectories.

**DexFlow** (``method: dexflow``) minimises, over the trajectory ``q_1..q_T``,

    E = Σ_t w_t Σ_i ρ(||v_H^i(t) - v_R^i(q_t)||²)                     (alignment, N keypoints)
      + α Σ_t ||q_t - q_{t-1}||²                                        (velocity)
      + λ Σ_t ||q_t - 2 q_{t-1} + q_{t-2}||²_{Σ⁻¹}                      (differential)
      + γ Σ_t ||q_t - q_t^pred||²,  q_t^pred = q_{t-1} + Δt q̇_{t-1}    (prediction)

with ``q̇_{t-1} = (q_{t-1} - q_{t-2}) / Δt`` (so the prediction term penalises acceleration in
plain joint units, the differential term in units of Σ). ``Σ`` is the kinematic covariance of
the joints, taken diagonal: each hand joint's variance is that of a uniform distribution over
its range, ``(upper - lower)² / 12``, so a joint with a large range may accelerate more; the
floating base uses ``base_sigma_m`` and ``base_sigma_rad``. ``ρ`` is the identity or, with
``robust_delta_m > 0``, a Huber loss on each keypoint's distance (iteratively reweighted).
``w_t`` is 0 on frames that carry no usable observation (NaN dropouts, ``valid = False``, or
tracking loss detected as a wrist jump): there only the temporal terms act, so the trajectory
is bridged smoothly through the gap and the bad frames never pull on their neighbours.

``window: 0`` optimises all frames jointly (every k-window of the paper is inside this sum);
``window: k`` solves the paper's causal sliding window: frames t-k+1..t are optimised with the
frames before them fixed, then the window moves on by one frame.

The solver is a projected Levenberg-Marquardt method: analytic keypoint Jacobians for all frames
in one batched forward-kinematics call, the temporal terms as a constant banded matrix, and
each step one banded Cholesky solve; joint limits hold by projection after every step and
coupled joints (tendons) are tied exactly by solving only for their leaders.

Initialisation: the floating base is a rigid fit (Kabsch) of the robot's palm keypoints to the
human's, frame by frame; the hand joints start from nlopt's ``GN_CRS2_LM`` global search as in
the paper, run on the first frame (``global_search: first_frame``), on every frame
(``every_frame``, the paper's exact setting, about a second a frame) or not at all (``off``).
Frames whose error jumps after solving are re-initialised by the global search and solved again.

**Baseline** (``method: position``): each frame on its own, the alignment term alone (the
position retargeting of dex-retargeting, warm-started from the previous frame), optionally
low-pass filtered afterwards; frames without an observation hold the last solution.

**One file** (about 620 lines): the objective's terms, the global search and the temporal pass share the
same batched tensors and notation (the equations in this docstring); each is a function of its own
here.
"""

from __future__ import annotations

import functools
import logging
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
from scipy.linalg import solveh_banded
from scipy.spatial.transform import Rotation

from dexflow.hands.files import staged_spec
from dexflow.hands.jacobian import KeypointJacobian
from dexflow.hands.robot import RobotHand, cached_hand
from dexflow.human.cleaning import detect_bad_frames, nearest_index
from dexflow.io.artifacts import Trajectory, write_trajectory
from dexflow.io.layout import Layout
from dexflow.io.sequence import Sequence, load_sequence
from dexflow.measures import fingertip_speeds, frame_chunks, rms_acceleration, velocity_kl
from dexflow.params import GlobalSearchParams, PipelineParams, RetargetParams
from dexflow.pipeline.resume import StageOutput
from dexflow.pipeline.runner import StageSpec

__all__ = [
    "STAGE",
    "RetargetResult",
    "retarget_sequence",
]

log = logging.getLogger(__name__)

_PALM_MANO = (0, 1, 5, 9, 13, 17)


@dataclass
class RetargetResult:
    """Outcome for one sequence (arrays over T frames).

    Attributes:
        q: (T, dof) joint trajectory, base first (``joint_names``).
        joint_names: Names of the columns of ``q``.
        keypoints_robot: (T, K, 3) robot keypoints.
        keypoints_human: (T, K, 3) the human targets they were matched to.
        error_m: (T,) mean keypoint distance per frame (NaN where unobserved).
        observed: (T,) frames whose keypoints were used.
        lost: (T,) frames detected as tracking loss.
        stats: Solver statistics.
    """

    q: np.ndarray
    joint_names: list[str]
    keypoints_robot: np.ndarray
    keypoints_human: np.ndarray
    error_m: np.ndarray
    observed: np.ndarray
    lost: np.ndarray
    stats: dict


class _Problem:
    """The free variables of a hand: joints that are not tied to another by a coupling."""

    def __init__(self, hand: RobotHand, params: RetargetParams, fps: float) -> None:
        self.hand, self.params = hand, params
        self.free = np.array(hand.free_joints)
        self.a, self.b = hand.coupling_affine()
        lower, upper = hand.lower.numpy(), hand.upper.numpy()
        self.lower, self.upper = lower[self.free], upper[self.free]
        sigma = np.concatenate(
            [
                [params.base_sigma_m] * 3,
                [params.base_sigma_rad] * 3,
                np.maximum((upper[6:] - lower[6:]) / np.sqrt(12.0), 1e-3),
            ]
        )
        inv_cov = np.diag(1.0 / sigma**2)
        # Temporal terms in free coordinates: velocity and acceleration weights (n x n).
        a, dof = self.a, hand.dof
        self.w_vel = params.alpha * a.T @ a
        self.w_acc = a.T @ (params.lambda_diff * inv_cov + params.gamma_pred * np.eye(dof)) @ a
        self.jacobian = KeypointJacobian(hand)
        self.dt = 1.0 / fps

    def full(self, x: np.ndarray) -> np.ndarray:
        return x @ self.a.T + self.b

    def project(self, x: np.ndarray) -> np.ndarray:
        return np.clip(x, self.lower, self.upper)

    def keypoints(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        kp, jac = self.jacobian(torch.as_tensor(self.full(x), dtype=self.hand.dtype))
        return kp.numpy(), jac.numpy() @ self.a  # (T,K,3), (T,K,3,n)

    def keypoints_only(self, x: np.ndarray) -> np.ndarray:
        """(T, K, 3) keypoints of ``x (T, n)`` as :meth:`keypoints` computes them, without the
        Jacobians and :func:`~dexflow.measures.frame_chunks` frames at a time: memory bounded
        whatever the sequence's length."""
        return np.concatenate([self.keypoints(x[s])[0] for s in frame_chunks(len(x))])


def _temporal_blocks(n_frames: int, w_vel: np.ndarray, w_acc: np.ndarray):
    """Blocks of the constant temporal Hessian: diagonal (T,n,n), first (T-1) and second
    (T-2) sub-diagonals, for velocity and acceleration terms over frames 1.. and 2.."""
    n = w_vel.shape[0]
    diag = np.zeros((n_frames, n, n))
    sub1 = np.zeros((max(n_frames - 1, 0), n, n))
    sub2 = np.zeros((max(n_frames - 2, 0), n, n))
    for t in range(1, n_frames):  # (q_t - q_{t-1})
        diag[t] += w_vel
        diag[t - 1] += w_vel
        sub1[t - 1] -= w_vel
    coef = (1.0, -2.0, 1.0)
    for t in range(2, n_frames):  # (q_t - 2 q_{t-1} + q_{t-2})
        rows = (t, t - 1, t - 2)
        for i in range(3):
            for j in range(3):
                ri, rj = rows[i], rows[j]
                if ri < rj:
                    continue
                block = coef[i] * coef[j] * w_acc
                if ri == rj:
                    diag[ri] += block
                elif ri - rj == 1:
                    sub1[rj] += block
                else:
                    sub2[rj] += block
    return diag, sub1, sub2


@functools.lru_cache(maxsize=4)
def _band_index(n_frames: int, n: int) -> tuple[np.ndarray, ...]:
    """Scatter indices from (diag, sub1, sub2) blocks into lower banded storage.

    About 60 KB a frame, so only the last few sizes are kept (a sequence's chunks have at most
    three: a whole chunk, the last one, a recovery's): a cache of every length a stage met grew
    with the data (0.16 MB per frame over a stage's sequences of many lengths)."""
    r, c = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    parts = []
    for offset, count in enumerate((n_frames, n_frames - 1, n_frames - 2)):
        keep = (offset * n + r - c >= 0) if offset == 0 else np.ones_like(r, dtype=bool)
        if count <= 0:
            parts.append(None)
            continue
        rows = np.broadcast_to((offset * n + r - c)[keep], (count, int(keep.sum())))
        cols = np.arange(count)[:, None] * n + c[keep][None]
        parts.append((rows.reshape(-1), cols.reshape(-1), r[keep], c[keep]))
    return tuple(parts)


def _to_banded(diag, sub1, sub2) -> np.ndarray:
    """Lower banded storage (solveh_banded) of the symmetric block-pentadiagonal matrix."""
    n_frames, n, _ = diag.shape
    ab = np.zeros((3 * n, n_frames * n))
    for blocks, part in zip((diag, sub1, sub2), _band_index(n_frames, n), strict=True):
        if part is not None:
            rows, cols, r, c = part
            ab[rows, cols] = blocks[:, r, c].reshape(-1)
    return ab


def _solve_lm(
    problem: _Problem,
    x0: np.ndarray,
    targets: np.ndarray,
    weights: np.ndarray,
    fixed: int,
    params: RetargetParams,
    temporal: bool,
) -> tuple[np.ndarray, dict]:
    """Projected Levenberg-Marquardt on frames ``fixed..T`` (earlier frames held).

    Args:
        x0: (T, n) initial free coordinates.
        targets: (T, K, 3) human keypoints (anything where the weight is 0).
        weights: (T,) per-frame alignment weight.
        fixed: Number of leading frames held fixed (they still enter temporal terms).
        temporal: Include the temporal terms (False: frames independent).
    """
    x = problem.project(x0.copy())
    n_frames, n = x.shape
    if temporal:
        diag_t, sub1_t, sub2_t = _temporal_blocks(n_frames, problem.w_vel, problem.w_acc)
    else:
        diag_t = np.zeros((n_frames, n, n))
        sub1_t, sub2_t = np.zeros((n_frames - 1, n, n)), np.zeros((max(n_frames - 2, 0), n, n))

    def temporal_energy_grad(x):
        if not temporal:
            return 0.0, np.zeros_like(x)
        grad = np.einsum("tij,tj->ti", diag_t, x)
        grad[1:] += np.einsum("tij,tj->ti", sub1_t, x[:-1])
        grad[:-1] += np.einsum("tji,tj->ti", sub1_t, x[1:])
        grad[2:] += np.einsum("tij,tj->ti", sub2_t, x[:-2])
        grad[:-2] += np.einsum("tji,tj->ti", sub2_t, x[2:])
        return 0.5 * float((x * grad).sum()), grad

    def align(x):
        kp, jac = problem.keypoints(x)
        res = kp - targets  # (T,K,3)
        dist = np.linalg.norm(res, axis=-1)
        if params.robust_delta_m > 0:
            delta = params.robust_delta_m
            rw = np.where(dist <= delta, 1.0, delta / np.maximum(dist, 1e-12))
            rho = np.where(dist <= delta, dist**2, 2 * delta * dist - delta**2)
        else:
            rw, rho = np.ones_like(dist), dist**2
        w = weights[:, None] * rw  # (T,K)
        energy = float((weights[:, None] * rho).sum())
        return energy, res, jac, w

    mu, evaluations = 1e-3, 0
    energy_a, res, jac, w = align(x)
    energy_t, grad_t = temporal_energy_grad(x)
    energy = energy_a + 2 * energy_t
    eye = np.eye(n)
    for _ in range(params.iterations):
        jf = jac.reshape(n_frames, -1, n)  # (T, 3K, n)
        jw = jf * np.repeat(w, 3, axis=1)[..., None]
        hess = np.swapaxes(jw, 1, 2) @ jf  # (T, n, n)
        grad = (np.swapaxes(jw, 1, 2) @ res.reshape(n_frames, -1, 1))[..., 0] + grad_t
        # Active set: a variable on a bound that the gradient pushes outwards stays there.
        at_bound = ((x <= problem.lower + 1e-12) & (grad > 0)) | (
            (x >= problem.upper - 1e-12) & (grad < 0)
        )
        at_bound[:fixed] = True
        keep = (~at_bound).astype(np.float64)
        diag = (hess + diag_t) * keep[:, :, None] * keep[:, None, :]
        damping = mu * (1.0 + np.diagonal(hess, axis1=1, axis2=2))
        diag += eye * np.where(at_bound, 1.0, damping)[:, None, :]
        sub1 = sub1_t * keep[1:, :, None] * keep[:-1, None, :]
        sub2 = sub2_t * keep[2:, :, None] * keep[:-2, None, :]
        rhs = np.where(at_bound, 0.0, grad)
        active = slice(fixed, n_frames)
        ab = _to_banded(diag[active], sub1[fixed:], sub2[fixed:])
        try:
            step = -solveh_banded(ab, rhs[active].reshape(-1), lower=True, check_finite=False)
        except np.linalg.LinAlgError:
            mu *= 10
            continue
        candidate = x.copy()
        candidate[active] = problem.project(x[active] + step.reshape(-1, n))
        evaluations += 1
        e_a, r_c, j_c, w_c = align(candidate)
        e_t, g_t = temporal_energy_grad(candidate)
        new_energy = e_a + 2 * e_t
        if new_energy < energy:
            improvement = (energy - new_energy) / max(energy, 1e-18)
            x, energy, res, jac, w, grad_t = candidate, new_energy, r_c, j_c, w_c, g_t
            mu = max(mu / 5, 1e-9)
            if improvement < params.tolerance:
                break
        else:
            mu *= 5
            if mu > 1e8:
                break
    return x, {"energy": energy, "evaluations": evaluations}


def _global_search(
    problem: _Problem, x0: np.ndarray, target: np.ndarray, params: GlobalSearchParams
) -> np.ndarray:
    """nlopt global search of one frame's hand joints (base held), then returns free coords."""
    import nlopt

    hand_free = np.flatnonzero(problem.free >= 6)
    lower, upper = problem.lower[hand_free], problem.upper[hand_free]
    x = x0.copy()

    def objective(values, grad):
        x[hand_free] = values
        kp = problem.hand.keypoints(
            torch.as_tensor(problem.full(x[None]), dtype=problem.hand.dtype)
        )
        return float(((kp[0].numpy() - target) ** 2).sum())

    nlopt.srand(params.seed)
    opt = nlopt.opt(getattr(nlopt, params.algorithm), len(hand_free))
    opt.set_lower_bounds(lower)
    opt.set_upper_bounds(upper)
    opt.set_min_objective(objective)
    opt.set_maxeval(params.max_evals)
    with torch.no_grad():
        best = opt.optimize(np.clip(x0[hand_free], lower, upper))
    out = x0.copy()
    out[hand_free] = best
    return out


def _initial_base(hand: RobotHand, human: np.ndarray, observed: np.ndarray) -> np.ndarray:
    """(T, 6) floating-base coordinates from a rigid fit of palm keypoints, frame by frame."""
    mano = np.asarray(hand.mano_indices)
    palm = np.flatnonzero(np.isin(mano, _PALM_MANO))
    use = palm if len(palm) >= 3 else np.arange(len(mano))
    zero = hand.zero()
    zero[:, :6] = 0.0
    robot = hand.keypoints(zero)[0].detach().numpy()[use]
    base = np.zeros((len(human), 6))
    idx = np.flatnonzero(observed)
    if len(idx) == 0:
        return base
    # Kabsch on the centred points: R minimises Σ ||(h - h̄) - R (r - r̄)||², then t = h̄ - R r̄.
    target = human[idx][:, mano[use]]  # (T, P, 3)
    centre, target_centre = robot.mean(axis=0), target.mean(axis=1)
    centred = target - target_centre[:, None]
    # align_vectors(a, b) fits a ≈ R b for one frame at a time.
    rotation = Rotation.concatenate([Rotation.align_vectors(h, robot - centre)[0] for h in centred])
    base[idx, :3] = target_centre - rotation.apply(centre)
    base[idx, 3:] = rotation.as_euler("XYZ")  # the floating base's Rx Ry Rz (base_transform)
    # Unobserved frames: nearest observed frame; unwrap angles so the base moves continuously.
    base = base[nearest_index(idx, len(human))]
    base[:, 3:] = np.unwrap(base[:, 3:], axis=0)
    return base


def retarget_sequence(seq: Sequence, hand: RobotHand, params: RetargetParams) -> RetargetResult:
    """Retarget one (scaled) sequence to ``hand``. See the module docstring for the method."""
    start = time.perf_counter()
    human_all = np.asarray(seq.keypoints, dtype=np.float64)
    observed, lost = detect_bad_frames(
        seq.keypoints, seq.valid, params.jump_threshold_m, fps=seq.fps
    )
    mano = np.asarray(hand.mano_indices)
    human = np.nan_to_num(human_all[:, mano])
    problem = _Problem(hand, params, seq.fps)
    n_frames = len(human)

    base = _initial_base(hand, human_all, observed)
    x0 = np.tile(problem.project(hand.zero().numpy()[0][problem.free]), (n_frames, 1))
    base_cols = np.flatnonzero(problem.free < 6)
    x0[:, base_cols] = base[:, problem.free[base_cols]]
    weights = observed.astype(np.float64)
    stats = {"global_searches": 0, "recoveries": 0, "evaluations": 0}
    mode = params.global_search.mode
    if mode not in ("first_frame", "every_frame", "off"):
        raise ValueError(
            f"retarget.global_search.mode: expected first_frame|every_frame|off, found {mode!r}"
        )

    if params.method == "position":
        x = _solve_position(problem, x0, human, observed, params, stats)
    elif params.method == "dexflow":
        obs = np.flatnonzero(observed)
        search = obs[:1] if mode == "first_frame" else obs if mode == "every_frame" else []
        for t in search:
            x0[t] = _global_search(problem, x0[t], human[t], params.global_search)
            stats["global_searches"] += 1
        if mode == "first_frame" and len(obs):
            x0[:, problem.free >= 6] = x0[obs[0], problem.free >= 6]
        x = _solve_dexflow(problem, x0, human, weights, params, stats)
        x = _recover(problem, x, human, weights, observed, params, stats)
    else:
        raise ValueError(
            f"retarget.method: expected 'dexflow' or 'position', found {params.method!r}"
        )

    q = hand.clamp(torch.as_tensor(problem.full(x))).numpy()
    with torch.no_grad():
        robot = np.concatenate(
            [hand.keypoints(torch.as_tensor(q[s])).numpy() for s in frame_chunks(len(q))]
        )
    error = np.linalg.norm(robot - human, axis=-1).mean(axis=-1)
    error[~observed] = np.nan
    stats["seconds"] = time.perf_counter() - start
    return RetargetResult(q, list(hand.joint_names), robot, human, error, observed, lost, stats)


def _solve_dexflow(problem, x0, human, weights, params, stats) -> np.ndarray:
    n_frames = len(x0)
    if params.window <= 0 or params.window >= n_frames:
        return _solve_chunked(problem, x0, human, weights, params, stats)
    x = x0.copy()
    k = params.window
    x[:k], info = _solve_lm(problem, x0[:k], human[:k], weights[:k], 0, params, temporal=True)
    for t in range(k, n_frames):
        lo = max(0, t - k + 1 - 2)  # two held frames give the window its velocity and acceleration
        held = t - k + 1 - lo
        init = x[lo : t + 1].copy()
        init[-1] = x[t - 1]
        sol, info = _solve_lm(
            problem, init, human[lo : t + 1], weights[lo : t + 1], held, params, True
        )
        x[lo + held : t + 1] = sol[held:]
        stats["evaluations"] += info["evaluations"]
    return x


def _solve_chunked(problem, x0, human, weights, params, stats) -> np.ndarray:
    """The offline solve of all frames at once; a sequence longer than ``chunk_frames`` is
    solved chunk after chunk, so that memory (the per-frame Jacobians and banded blocks, about
    0.2 MB a frame) is bounded by a chunk: each chunk starts ``chunk_overlap`` frames before the
    end of the last, solves those frames again knowing what follows them, and holds the two
    frames before them as solved (they carry the velocity and acceleration across)."""
    n_frames, chunk = len(x0), params.chunk_frames
    if chunk <= 0 or n_frames <= chunk:
        x, info = _solve_lm(problem, x0, human, weights, 0, params, temporal=True)
        stats["evaluations"] += info["evaluations"]
        return x
    x, start, held = x0.copy(), 0, 0
    while True:
        end = min(start + chunk, n_frames)
        sol, info = _solve_lm(
            problem, x[start:end], human[start:end], weights[start:end], held, params, True
        )
        x[start + held : end] = sol[held:]
        stats["evaluations"] += info["evaluations"]
        if end == n_frames:
            return x
        start, held = end - params.chunk_overlap - 2, 2


def _recover(problem, x, human, weights, observed, params, stats) -> np.ndarray:
    """Re-initialise frames whose error jumped (tracking lost) by global search; solve again."""
    if params.global_search.mode == "off" or params.max_recoveries <= 0:
        return x
    kp = problem.keypoints_only(x)
    error = np.linalg.norm(kp - human, axis=-1).mean(axis=-1)
    obs = np.flatnonzero(observed)
    if len(obs) == 0:
        return x
    limit = max(params.recover_error_m, params.recover_factor * np.median(error[obs]))
    bad = obs[error[obs] > limit][: params.max_recoveries]
    if len(bad) == 0:
        return x
    x0 = x.copy()
    for t in bad:
        x0[t] = _global_search(problem, x[t], human[t], params.global_search)
        stats["global_searches"] += 1
    stats["recoveries"] += len(bad)
    candidate = _solve_dexflow(problem, x0, human, weights, params, stats)
    kp_c = problem.keypoints_only(candidate)
    better = np.linalg.norm(kp_c - human, axis=-1).mean(axis=-1)[obs].mean() < error[obs].mean()
    return candidate if better else x


def _solve_position(problem, x0, human, observed, params, stats) -> np.ndarray:
    """Per-frame alignment (warm-started frame to frame); unobserved frames hold."""
    x = x0.copy()
    previous = None
    for t in range(len(x)):
        if not observed[t]:
            if previous is not None:
                x[t] = previous
            continue
        init = x0[t : t + 1].copy()
        if previous is not None:
            init[0, problem.free >= 6] = previous[problem.free >= 6]
        sol, info = _solve_lm(
            problem, init, human[t : t + 1], np.ones(1), 0, params, temporal=False
        )
        x[t] = previous = sol[0]
        stats["evaluations"] += info["evaluations"]
    if params.lowpass_hz > 0:
        from scipy.signal import butter, filtfilt

        nyquist = 0.5 / problem.dt
        if params.lowpass_hz < nyquist and len(x) > 12:
            b, a = butter(2, params.lowpass_hz / nyquist)
            x = problem.project(filtfilt(b, a, x, axis=0))
    return x


def save_result(path: str | Path, result: RetargetResult, seq: Sequence) -> None:
    """Write a result as a :class:`~dexflow.io.artifacts.Trajectory` (q with joint names, plus
    keypoints, errors, masks, stats)."""
    arrays = {
        "keypoints_robot": result.keypoints_robot,
        "keypoints_human": result.keypoints_human,
        "keypoint_error_m": result.error_m,
        "observed": result.observed,
        "lost": result.lost,
        "fps": np.array(seq.fps),
        "global_searches": np.array(result.stats["global_searches"]),
        "recoveries": np.array(result.stats["recoveries"]),
        "evaluations": np.array(result.stats["evaluations"]),
    }
    write_trajectory(path, Trajectory(result.q, list(result.joint_names), arrays))


def _sequence_metrics(result: RetargetResult, hand: RobotHand, seq: Sequence) -> dict:
    """The stage's per-sequence statistics. ``keypoint_error_mm`` and ``rms_acc`` are the
    metrics stage's definitions (:mod:`dexflow.stages.metrics`); ``*_gt`` compare with the demo's
    clean, true hand (only there). The velocity KL against the observed hand is the metrics
    stage's alone (pooled over sequences)."""
    fps = seq.fps
    tips = hand.fingertip_keypoints
    observed = result.observed
    out = {
        "frames": len(result.q),
        "observed_frames": int(observed.sum()),
        "lost_frames": int(result.lost.sum()),
        "keypoint_error_mm": float(np.nanmean(result.error_m) * 1000),
        "rms_acc": rms_acceleration(result.q[:, 6:], fps),
        "global_searches": int(result.stats["global_searches"]),
        "recoveries": int(result.stats["recoveries"]),
    }
    if "gt_keypoints" in seq.extras:  # generated data: compare with the clean, true hand too
        truth = np.asarray(seq.extras["gt_keypoints"])[:, hand.mano_indices]
        out["keypoint_error_gt_mm"] = float(
            np.linalg.norm(result.keypoints_robot - truth, axis=-1).mean(axis=-1)[observed].mean()
            * 1000
        )
        robot = fingertip_speeds(result.keypoints_robot[:, tips], fps, observed)
        out["velocity_kl_gt"] = velocity_kl(fingertip_speeds(truth[:, tips], fps, observed), robot)
    return out


def run_retarget(params: PipelineParams, layout: Layout, method: str = "dexflow") -> dict:
    """Stage runner: every sequence of ``layout.scale_align`` -> ``layout.retarget(method)``.

    Returns:
        The summary (also written to the stage's ``summary.json``), with the wall-clock speed
        under ``timing`` (returned, not written there).
    """
    source, out = layout.scale_align, layout.retarget(method)
    rparams = replace(params.retarget, method=method)
    stage = StageOutput(
        out,
        f"retarget {method}",
        {"seed": params.seed, "hand": params.hand, "retarget": rparams},
        inputs=(source, layout.hand_files),
    )
    files = stage.start()
    spec = staged_spec(params.hand, layout.hand_files.root)

    def one(path: Path) -> dict:
        torch.set_num_threads(1)
        hand = cached_hand(spec, None)
        seq = load_sequence(path, data_root=source.root)
        result = retarget_sequence(seq, hand, rparams)
        save_result(out.sequence(path), result, seq)
        return _sequence_metrics(result, hand, seq)

    tally = stage.run(one, files, params.run)
    sequences, ok, seconds = tally.sequences, tally.ok, tally.seconds
    frames = sum(s["frames"] for s in ok)

    def mean(key):
        values = [s[key] for s in ok if np.isfinite(s[key])]
        return float(np.mean(values)) if values else float("nan")

    summary = {
        "stage": "retarget",
        "method": method,
        "hand": spec.name,
        "num_sequences": len(files),
        "num_ok": len(ok),
        "num_failed": len(files) - len(ok),
        "num_frames": frames,
        "keypoint_error_mm": mean("keypoint_error_mm"),
        "rms_acc": mean("rms_acc"),
        **(
            {k: mean(k) for k in ("keypoint_error_gt_mm", "velocity_kl_gt")}
            if ok and "velocity_kl_gt" in ok[0]
            else {}
        ),
        "sequences": dict(sorted(sequences.items())),
    }
    stage.finish(summary)
    return {**summary, "timing": {"frames_per_second": frames / seconds if seconds else 0.0}}


STAGE = StageSpec(
    name="retarget",
    run=run_retarget,
    metric_keys=("num_sequences", "num_ok", "num_failed", "num_frames", "keypoint_error_mm",
                 "rms_acc", "keypoint_error_gt_mm", "velocity_kl_gt"),
    describe=lambda s: (
        f"{s['num_ok']}/{s['num_sequences']} sequences ok, {s['num_frames']} frames, "
        f"{s['timing']['frames_per_second']:.1f} frames/s, error {s['keypoint_error_mm']:.2f} mm, "
        f"RMS joint acc {s['rms_acc']:.2f} rad/s^2"
    ),
)  # fmt: skip
