"""Experiments of Raunhardt & Boulic (2007), section 5, on the coupled-spine models (paper reproduction).

Task sets of the isolated-spine experiment (5.1), the balanced posture (5.2.1)
and the figure-eight periodic task with its joint-space drift (5.2.2), solved
by `kinematics.algorithms.prioritized.PrioritizedIK` on the models of
`kinematics.mechanisms.spine`.  Used by benchmarks/spine.py and tests/test_spine.py.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from kinematics.algorithms.fk import marker_positions
from kinematics.algorithms.prioritized import PrioritizedIK
from kinematics.algorithms.tasks import KinematicTasks, Task
from kinematics.mechanisms.spine_measures import posture_distance, spine_coordinates, spine_distance
from kinematics.multibody.model import Model

__all__ = ["isolated_spine_tasks", "balanced_posture_tasks", "FigureEight", "periodic_tasks", "periodic_drift"]


def isolated_spine_tasks(model: Model, kt: KinematicTasks | None = None,
                         orientation_rotvec=(0.15, 0.35, -0.3), position=(0.15, 0.70, 0.10)) -> list[Task]:
    """Experiment 5.1: head orientation (priority 0, rotation vector in rad) and head-top position (priority 1, m)."""
    kt = kt or KinematicTasks(model)
    Rt = Rotation.from_rotvec(orientation_rotvec).as_matrix()
    return [kt.orientation("head orientation", "skull", Rt, 0),
            kt.position("head position", "skull", (0.0, 0.2, 0.0), np.asarray(position, float), 1)]


def _marker_point(model: Model, name: str):
    mk = model.marker(name)
    return mk.body, mk.offset


def _hand_recruits(model: Model, kt: KinematicTasks, body: str, pelvis: bool = True) -> tuple[str, ...]:
    """A hand recruits its ancestors (without the pelvis when ``pelvis`` is False) and the whole
    spine: the cervical joints are coupled to the thoracic ones (inter-region inequalities), so
    eq. (4) requires the hand to recruit them too whenever a lower-priority task (the head) moves them."""
    anc = tuple(c for c in kt.ancestors(body) if pelvis or not c.startswith("pelvis_"))
    return anc + tuple(c for c in spine_coordinates(model) if c not in anc)


def balanced_posture_tasks(model: Model, kt: KinematicTasks | None = None, q0=None) -> list[Task]:
    """Experiment 5.2.1 on a mannequin (targets relative to the posture q0, metres).

    priority 0: centre of mass (x, z) over the middle of the left foot;
    priority 1: left heel, toe and lateral forefoot stay where they are (the seed uses heel and
    toe only, which leaves the foot free to roll about the heel-toe line);
    priority 2: right toe 0.35 m backwards and 0.15 m up, both hands reach forward-left;
    priority 3: head keeps looking forward (identity orientation).
    """
    kt = kt or KinematicTasks(model)
    q0 = model.default_q if q0 is None else np.asarray(q0, float)
    x0 = dict(zip(model.marker_names, marker_positions(model, q0)))
    support = 0.5 * (x0["l_heel"] + x0["l_toe"])
    tasks = [kt.com("centre of mass over left foot", support[[0, 2]], 0)]
    for m in ("l_heel", "l_toe", "l_toe_lat"):
        body, off = _marker_point(model, m)
        tasks.append(kt.position(f"{m} on the ground", body, off, x0[m], 1))
    body, off = _marker_point(model, "r_toe")
    tasks.append(kt.position("right toe backwards", body, off, x0["r_toe"] + np.array([-0.35, 0.15, 0.0]), 2))
    for m, dz in (("r_hand", -0.25), ("l_hand", -0.15)):
        body, off = _marker_point(model, m)
        target = np.array([0.45, 1.15, x0[m][2] + dz])
        tasks.append(kt.position(f"{m} reaching", body, off, target, 2, recruited=_hand_recruits(model, kt, body)))
    tasks.append(kt.orientation("head looking forward", "skull", np.eye(3), 3))
    return tasks


class FigureEight:
    """Moving goal on a figure eight in the frontal (y-z) plane: z = a sin(phase), y = b sin(2 phase).

    ``phase`` (rad) is set by the caller; `target(offset)` returns a callable for a task.
    """

    def __init__(self, centre, a: float = 0.15, b: float = 0.08):
        self.centre = np.asarray(centre, float)
        self.a, self.b = float(a), float(b)
        self.phase = 0.0

    def point(self, offset=(0.0, 0.0, 0.0)) -> np.ndarray:
        p = self.phase
        return self.centre + np.asarray(offset, float) + np.array([0.0, self.b * np.sin(2 * p), self.a * np.sin(p)])

    def target(self, offset=(0.0, 0.0, 0.0)):
        off = np.asarray(offset, float)
        return lambda: self.point(off)


def periodic_tasks(model: Model, eight: FigureEight, kt: KinematicTasks | None = None, q0=None,
                   recruit_pelvis: bool = True) -> list[Task]:
    """Experiment 5.2.2: COM between the feet (0), three sole points per foot fixed (1), hands on the
    figure eight (2), head looking forward (3).

    Deviations from the seed, applied to both models: a third sole point per foot (heel and toe
    alone let the foot roll about their line, a null-space motion that drifts freely) and the
    head task (without it the head, moved only through the centre of mass, drifts freely).
    """
    kt = kt or KinematicTasks(model)
    q0 = model.default_q if q0 is None else np.asarray(q0, float)
    x0 = dict(zip(model.marker_names, marker_positions(model, q0)))
    feet = ("l_heel", "l_toe", "l_toe_lat", "r_heel", "r_toe", "r_toe_lat")
    support = np.mean([x0[m] for m in feet], axis=0)
    tasks = [kt.com("centre of mass between the feet", support[[0, 2]], 0)]
    for m in feet:
        body, off = _marker_point(model, m)
        tasks.append(kt.position(f"{m} on the ground", body, off, x0[m], 1))
    for m, dz in (("r_hand", 0.08), ("l_hand", -0.08)):
        body, off = _marker_point(model, m)
        tasks.append(kt.position(f"{m} on the figure eight", body, off, eight.target((0.0, 0.0, dz)), 2,
                                 recruited=_hand_recruits(model, kt, body, pelvis=recruit_pelvis), max_error=0.1))
    # the head keeps looking forward (as in 5.2.1): without it the head, moved only through the
    # centre of mass, would drift freely in both models
    head = tuple(c for c in kt.ancestors("skull") if recruit_pelvis or not c.startswith("pelvis_"))
    tasks.append(kt.orientation("head looking forward", "skull", np.eye(3), 3, recruited=head))
    return tasks


def periodic_drift(model: Model, cycles: int = 2000, steps_per_cycle: int = 24,
                   checkpoints: Sequence[int] = (5, 50, 100, 200, 600, 2000), settle: int = 60,
                   centre=(0.40, 1.15, 0.0), progress=None) -> dict:
    """Run the figure-eight task for `cycles` cycles; joint-space drift at the checkpoints.

    One IK step per goal sample, `steps_per_cycle` samples per cycle.  Drift
    after c cycles is |q(c) - q(1)| over the rotational coordinates (rad) with
    q(c) the posture at the end of cycle c; also the geodesic distances of the
    spine (`spine_distance`) and of the whole posture (`posture_distance`).
    ``settle`` steps first converge on the goal at phase 0.

    Returns dict with 'drift_rad' (Euclidean over rotational coordinates), 'drift_spine_rad'
    (`spine_distance`), 'drift_posture_rad' (`posture_distance`) (checkpoint -> rad),
    'postures' (checkpoint -> q), 'max_task_error' per level (m), 'max_equality_residual'
    (after every cycle), 'max_inequality_or_limit_excess' (after every step; <= 0 when never violated).
    """
    eight = FigureEight(centre)
    kt = KinematicTasks(model)
    ik = PrioritizedIK.from_model(model, periodic_tasks(model, eight, kt))
    q = model.default_q.copy()
    for _ in range(settle):
        q = ik.step(q).q
    rot = model.rotational
    ref = None
    drift, drift_spine, drift_posture, postures = {}, {}, {}, {}
    max_err = np.zeros(len(ik.levels))
    cons = ik.constraints
    max_res = 0.0
    max_excess = -np.inf
    wanted = set(int(c) for c in checkpoints if c <= cycles)
    for c in range(1, cycles + 1):
        for k in range(steps_per_cycle):
            eight.phase = 2 * np.pi * (k + 1) / steps_per_cycle
            r = ik.step(q)
            q = r.q
            max_err = np.maximum(max_err, r.errors)
            max_excess = max(max_excess, float(np.max(cons.inequality_excess(q), initial=0.0)),
                             float(np.max(ik.lower - q)), float(np.max(q - ik.upper)))
        if len(cons.b):
            max_res = max(max_res, float(np.max(np.abs(cons.equality_residual(q)))))
        if c == 1:
            ref = q.copy()
            postures[1] = ref
        if c in wanted:
            drift[c] = float(np.linalg.norm((q - ref)[rot]))
            drift_spine[c] = spine_distance(model, q, ref)
            drift_posture[c] = posture_distance(model, q, ref)
            postures[c] = q.copy()
        if progress is not None:
            progress(c)
    return {"drift_rad": drift, "drift_spine_rad": drift_spine, "drift_posture_rad": drift_posture,
            "postures": postures,
            "max_task_error": max_err.tolist(), "max_equality_residual": max_res,
            "max_inequality_or_limit_excess": max_excess}
