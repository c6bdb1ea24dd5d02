"""Inverse dynamics of a whole trial: filtered coordinates, ground reactions, joint moments and powers.

For the coordinates q_k at times t_k (an IK result), the pipeline is

1. low-pass q (`kinematics.gait.filtering.lowpass`; by default OpenSim's
   InverseDynamicsTool filter: N/2 reflected padding, 3rd-order Butterworth
   forward and backward at the cut-off),
2. an interpolating natural quintic spline through the filtered samples
   (padding included, as OpenSim's GCVSplineSet) gives q, qd, qdd at t_k,
3. each external load (force F, point p, free torque T, ground frame) is
   interpolated at t_k by a natural cubic spline (OpenSim's ExternalForce
   uses an interpolating cubic GCV spline) and applied to its body as the
   wrench (F, T + (p - o_b) x F) at the body origin o_b,
4. the generalised forces follow from the transmission chain
   (`kinematics.mechanisms.dynamics.inverse_dynamics`, Taendl et al. eq. 24):

       tau = M(q) qdd + C(q, qd) qd - G(q) - sum_loads J_b(q)^T w_b

   and the joint powers P = tau * qd (W; N m x rad/s or N x m/s).

Moments are N m for rotational coordinates, N for translational ones (the
"*_moment" / "*_force" columns of OpenSim's output), in the model's
coordinate directions; ``per_kg`` divides by the model's mass.

Checked against OpenSim's InverseDynamicsTool on subject01_walk1 (the same
files, 6 Hz): every column within 1e-5 of its peak (RMS).  Loads from a C3D
trial come from `loads_from_c3d` (plates assigned to feet, rotated into the
model's ground); frames whose ground reaction is unknown (two feet on a
plate, a CoP outside its plate, a foot standing off the plates, no load data)
are NaN, never computed with a missing ground reaction.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lowerlimb.errors import InputError
from kinematics.io.external_loads import ExternalLoad
from kinematics.gait.filtering import DEFAULT_CUTOFF_HZ, _opensim_lowpass, lowpass
from kinematics.multibody.model import Model
from kinematics.mechanisms.transmission import AppliedLoad, TransmissionChain

__all__ = ["InverseDynamicsResult", "TrialLoads", "lab_to_ground", "loads_from_c3d", "trial_inverse_dynamics", "write_inverse_dynamics",
           "write_joint_powers"]


@dataclass(frozen=True)
class InverseDynamicsResult:
    """Generalised forces of a trial.

    Attributes
    ----------
    coordinates : tuple of str, length C (model order)
    kinds : tuple of str
        ``"rotational"`` / ``"translational"`` per coordinate.
    time : ndarray (F,), s
    q, qd, qdd : ndarray (F, C)
        Filtered coordinates (rad, m) and their derivatives.
    tau : ndarray (F, C)
        Generalised forces, N m (rotational) or N (translational).
    power : ndarray (F, C)
        tau * qd, W.
    mass : float, kg
        Model mass (for the per-kg values).
    loads : tuple of str
        Bodies that received external loads.
    notes : tuple of str
    """

    coordinates: tuple
    kinds: tuple
    time: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    tau: np.ndarray
    power: np.ndarray
    mass: float
    loads: tuple = ()
    notes: tuple = field(default=(), compare=False)

    @property
    def labels(self) -> list[str]:
        """OpenSim column names: ``<coordinate>_moment`` or ``<coordinate>_force``."""
        return [f"{c}_{'force' if k == 'translational' else 'moment'}" for c, k in zip(self.coordinates, self.kinds)]

    @property
    def tau_per_kg(self) -> np.ndarray:
        return self.tau / self.mass

    @property
    def power_per_kg(self) -> np.ndarray:
        return self.power / self.mass

    def __getitem__(self, name: str) -> np.ndarray:
        """Generalised force of one coordinate (by coordinate name or OpenSim label), shape (F,)."""
        for i, (c, lab) in enumerate(zip(self.coordinates, self.labels)):
            if name in (c, lab):
                return self.tau[:, i]
        raise KeyError(name)


def _interp_cubic(t_data, values, t, margin: int = 60):
    """Natural cubic spline through (t_data, values) at t; fitted on the samples around t only.

    A natural spline's dependence on a sample decays by ~0.27 per knot, so
    leaving out samples more than `margin` knots away from every t changes
    nothing measurable (OpenSim fits all samples).
    """
    from scipy.interpolate import CubicSpline

    i0 = max(int(np.searchsorted(t_data, t.min())) - margin, 0)
    i1 = min(int(np.searchsorted(t_data, t.max())) + margin, len(t_data))
    td, vd = t_data[i0:i1], values[i0:i1]
    if len(td) < 4:
        return np.column_stack([np.interp(t, t_data, values[:, i]) for i in range(values.shape[1])])
    return CubicSpline(td, vd, bc_type="natural", axis=0)(t)


def trial_inverse_dynamics(model: Model, time, q, loads: Sequence[ExternalLoad] = (), *,
                           cutoff: float | None = DEFAULT_CUTOFF_HZ, method: str = "opensim",
                           load_cutoff: float | None = None, start: float | None = None, end: float | None = None,
                           exclude: Sequence[tuple] = (), max_point_distance: float = 0.5,
                           chain: TransmissionChain | None = None) -> InverseDynamicsResult:
    """Joint moments and powers of a trial (module docstring for the model).

    Parameters
    ----------
    model : Model
    time : ndarray (F,), s, uniformly sampled
    q : ndarray (F, C), SI (rad, m), columns in ``model.coordinate_names`` order
    loads : external loads (ground frame; OpenSim's Y-up ground for OpenSim models)
    cutoff : float or None, Hz
        Low-pass cut-off of the coordinates; None: not filtered.
    method : {"opensim", "winter"}
        `kinematics.gait.filtering.lowpass` method.
    load_cutoff : float or None, Hz
        Low-pass the loads' force and moment about the ground origin (the
        coordinates' zero-lag filter, `method`) before use; None keeps them as given (OpenSim's tool).
    start, end : float, s
        Output window (the whole filtered trial is used for the splines).
    exclude : sequence of (t0, t1, reason)
        Time intervals whose ground reaction is unknown (e.g. a plate with two
        feet on it): their generalised forces are NaN, with a note.
    max_point_distance : float, m
        A load whose point of application is farther than this from its body's
        origin in most loaded frames (median) is refused: kinematics and loads
        are then not in the same frame or time base.

    Returns
    -------
    InverseDynamicsResult
    """
    from kinematics.gait.filtering import derivatives

    t = np.asarray(time, float).ravel()
    q = np.asarray(q, float)
    n = model.n_q
    if q.ndim != 2 or q.shape != (t.shape[0], n):
        raise InputError("coordinates", f"array of shape {q.shape} for {t.shape[0]} times x {n} model coordinates")
    if t.shape[0] < 6:
        raise InputError("coordinates", "at least 6 frames are needed")
    dt = np.diff(t)
    if np.any(dt <= 0) or (dt.max() - dt.min()) > 1e-3 * np.median(dt):
        j = int(np.argmax(np.abs(dt - np.median(dt))))
        raise InputError("coordinates", f"times must be uniformly sampled and increasing (step {dt[j]:.4g} s at "
                                        f"{t[j]:.4f} s, elsewhere {np.median(dt):.4g} s: frames missing?)")
    if not np.all(np.isfinite(q)):
        raise InputError("coordinates", "coordinates contain NaN; the IK left frames unsolved")
    rate = 1.0 / dt.mean()
    notes = []
    if cutoff is not None and cutoff > 0:
        if method == "opensim":
            pad = t.shape[0] // 2
            qp = _opensim_lowpass(q, rate, cutoff, padded=True)
            tp = t[0] + (np.arange(qp.shape[0]) - pad) / rate
            qs, qds, qdds = derivatives(qp, tp, 2)
            sl = slice(pad, pad + t.shape[0])
            qf, qd, qdd = qs[sl], qds[sl], qdds[sl]
        else:
            qf = lowpass(q, rate, cutoff, method=method, source="coordinates")
            qf, qd, qdd = derivatives(qf, t, 2)
        notes.append(f"coordinates low-pass filtered at {cutoff:g} Hz ({method})")
    else:
        qf, qd, qdd = derivatives(q, t, 2)
        notes.append("coordinates not filtered")
    keep = np.ones(t.shape[0], bool)
    if start is not None and start < t[0] - 1e-6:
        notes.append(f"requested start {start:g} s is before the first coordinate frame ({t[0]:g} s): "
                     "output starts there (no padded frames)")
    if end is not None and end > t[-1] + 1e-6:
        notes.append(f"requested end {end:g} s is after the last coordinate frame ({t[-1]:g} s)")
    if start is not None:
        keep &= t >= start - 1e-6
    if end is not None:
        keep &= t <= end + 1e-6
    if not keep.any():
        raise InputError("time range", f"no frame between {start} and {end} s")
    t, qf, qd, qdd = t[keep], qf[keep], qd[keep], qdd[keep]
    ch = chain or TransmissionChain(model)
    applied = []
    bodies = []
    unknown = np.zeros(t.shape[0], bool)
    state = ch.motion(qf, qd, qdd)  # one motion pass: body origins for the loads and the inertia loads
    if loads:
        for ld in loads:
            P = ld.point
            try:
                b = model.body_index(ld.body)
            except Exception:  # noqa: BLE001 - model lookups raise their own error types
                raise InputError(ld.name, f"load applied to body {ld.body!r}, which the model does not have") from None
            F, T = ld.force, ld.torque
            M = np.cross(P, F) + T  # moment about the ground origin: continuous through contact changes
            if load_cutoff is not None and load_cutoff > 0:
                lr = 1.0 / np.mean(np.diff(ld.time))
                # the coordinates' filter: kinematics and loads filtered alike keep their moments consistent
                F = lowpass(F, lr, load_cutoff, method=method, source=ld.name)
                M = lowpass(M, lr, load_cutoff, method=method, source=ld.name)
            FM = _interp_cubic(ld.time, np.hstack([F, M]), t)
            Fk, Mk = FM[:, :3], FM[:, 3:]
            outside = (t < ld.time[0] - 1e-9) | (t > ld.time[-1] + 1e-9)
            if outside.all():
                raise InputError(ld.name, f"no ground-reaction data in the kinematics' time range ({t[0]:.3f}-"
                                          f"{t[-1]:.3f} s; the loads cover {ld.time[0]:.3f}-{ld.time[-1]:.3f} s)")
            if outside.any():
                Fk[outside] = 0.0
                Mk[outside] = 0.0
                unknown |= outside
                notes.append(f"{ld.name}: no load data for {int(outside.sum())} frames: moments not computed there")
            ob = state.bodies[b].r
            Pk = _interp_cubic(ld.time, P, t)
            on = np.linalg.norm(Fk, axis=1) > 20.0
            if on.sum() >= 3:
                d = float(np.median(np.linalg.norm(Pk[on] - ob[on], axis=1)))
                if d > max_point_distance:
                    raise InputError(ld.name, f"its point of application is {d:.2f} m from body {ld.body!r} (median "
                                              "over the loaded frames): loads and kinematics are not in the same "
                                              "frame or time base")
            applied.append(AppliedLoad(ld.body, Fk, np.zeros((t.shape[0], 3)), Mk - np.cross(ob, Fk)))
            bodies.append(ld.body)
        if load_cutoff:
            notes.append(f"loads low-pass filtered at {load_cutoff:g} Hz")
    else:
        notes.append("no external loads: kinematics-driven moments only (no ground reactions)")
    tau = -ch.force(state, applied, model.gravity, inertia=True)  # = dynamics.inverse_dynamics
    tau[unknown] = np.nan
    for t0, t1, why in exclude:
        bad = (t >= t0 - 1e-9) & (t <= t1 + 1e-9)
        if bad.any():
            tau[bad] = np.nan
            notes.append(f"{int(bad.sum())} frames {t0:.3f}-{t1:.3f} s not computed: {why}")
    return InverseDynamicsResult(tuple(model.coordinate_names), tuple(c.kind for c in model.coordinates), t, qf, qd, qdd, tau,
                                 tau * qd, model.total_mass, tuple(bodies), tuple(notes))


def write_inverse_dynamics(path, result: InverseDynamicsResult, per_kg: bool = False) -> Path:
    """Write generalised forces as OpenSim's InverseDynamicsTool does (``*_moment`` / ``*_force`` columns)."""
    from kinematics.io.storage import write_sto

    vals = result.tau_per_kg if per_kg else result.tau
    unit = "N m/kg (rotational), N/kg (translational)" if per_kg else "N m (rotational), N (translational)"
    return write_sto(path, result.labels, result.time, vals, name="Inverse Dynamics",
                     header_extra=[f"Generalized forces in {unit}, along the model's coordinates;",
                                   f"model mass {result.mass:.3f} kg"])


def write_joint_powers(path, result: InverseDynamicsResult, per_kg: bool = False) -> Path:
    """Joint powers tau * qd (W or W/kg), one ``<coordinate>_power`` column per coordinate."""
    from kinematics.io.storage import write_sto

    vals = result.power_per_kg if per_kg else result.power
    return write_sto(path, [f"{c}_power" for c in result.coordinates], result.time, vals, name="Joint powers",
                     header_extra=[f"Joint powers tau * qd in {'W/kg' if per_kg else 'W'};",
                                   f"model mass {result.mass:.3f} kg"])


def lab_to_ground(model: Model, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Rotation from a lab whose vertical is `up` (a signed lab axis; C3D labs +Z) to the model's ground.

    The model's vertical is minus its gravity.  The rotation is the signed permutation that takes the
    lab's vertical to the model's and the lab's first horizontal axis (X unless X is up) to the model's
    (`kinematics.io.external_loads.axis_permutation`): a Z-up lab to a gravity -Z model is the identity;
    to OpenSim's -Y gravity x' = x, y' = z, z' = -y (the usual C3D to OpenSim export, ``LAB_TO_OPENSIM``);
    a Y-up lab to a -Y model the identity.  It assumes the kinematics were solved on the lab's markers
    re-expressed the same way (as OpenSim's exports and `personalize ik` on a lab's own TRC do).
    """
    from kinematics.io.external_loads import axis_permutation

    g = np.asarray(model.gravity, float)
    if not np.linalg.norm(g) > 0:
        raise InputError(model.name or "model", "has no gravity: cannot tell its vertical")
    u = -g / np.linalg.norm(g)
    if np.abs(u).max() < 1.0 - 1e-6:
        raise InputError(model.name or "model", f"gravity {g} is not along an axis: the lab-to-ground rotation is unknown")
    return axis_permutation(np.asarray(up, float), np.round(u))


@dataclass(frozen=True)
class TrialLoads:
    """Ground reactions of a C3D trial in a model's ground, with what could not be applied.

    Attributes
    ----------
    loads : tuple of ExternalLoad (one per foot that stood on a plate)
    contacts : tuple of PlateContact (`kinematics.gait.plate_contacts.assign_feet`)
    exclude : tuple of (t0, t1, reason)
        Loaded intervals that cannot be applied to one foot (two feet, CoP
        outside the plate, no foot found): pass to `trial_inverse_dynamics`.
    notes : tuple of str
    """

    loads: tuple
    contacts: tuple
    exclude: tuple
    notes: tuple


def loads_from_c3d(path, model: Model, *, threshold: float = 20.0, bodies: dict | None = None,
                   rotation: np.ndarray | None = None) -> TrialLoads:
    """Force plates of a C3D trial as external loads on the model's feet.

    The plates are read at the point rate (box-averaged, as Nexus reports them; raw analog noise
    would put low-load centres of pressure outside the plates), each loaded
    interval is assigned to a foot from the file's foot markers
    (`assign_feet`), the wrenches are summed per foot (`loads_from_plates`)
    and rotated into the model's ground (`lab_to_ground`).  The lab's vertical is read from the
    file's markers (`kinematics.gait.lab_frame.detect_lab`; +Z, the C3D convention, when they do not
    tell it, with a note): a Y-up lab's plates are read and rotated as such.  Feet go to
    ``calcn_r`` / ``calcn_l`` (``bodies`` to change).  A file without plates
    gives no loads and a note.  ``rotation`` (3, 3): x_ground = rotation @ x_lab, for a model whose ground is
    not the lab's axes permuted to Y up (`lab_to_ground`, the default), e.g. a personalised model's ground,
    which faces the static pose's direction (same origin as the lab).
    """
    from kinematics.io.c3d import read_c3d
    from kinematics.io.external_loads import loads_from_plates
    from kinematics.gait.plate_contacts import assign_feet
    from kinematics.io.forceplates import read_force_plates

    markers = read_c3d(path)
    lab_notes: list[str] = []
    up = _lab_up(markers, lab_notes)
    plates = read_force_plates(path, threshold=threshold, at="points", up=up)
    notes = list(plates.notes)
    for p in plates:
        notes += [f"{p.name}: {n}" for n in p.notes]
    if len(plates) == 0:
        return TrialLoads((), (), (), tuple(notes))
    notes += lab_notes
    bodies = dict(bodies or {"R": "calcn_r", "L": "calcn_l"})
    missing = [b for b in bodies.values() if b not in model.body_names]
    if missing:
        raise InputError(model.name or "model", f"has no body {', '.join(missing)} to apply the ground reactions to")
    contacts = assign_feet(plates, markers)
    if not contacts:
        notes.append(f"no force plate is loaded above {threshold:g} N: no ground reactions, kinematics only")
        return TrialLoads((), (), (), tuple(notes))
    R = lab_to_ground(model, up) if rotation is None else np.asarray(rotation, float)
    loads, _ = loads_from_plates(plates, contacts, bodies, rotation=R, up=up)
    notes += [c.describe() for c in contacts]
    exclude = [(c.start_time, c.end_time, f"plate {c.plate + 1}: {', '.join(c.flags) or 'no foot'}")
               for c in contacts if not c.usable]
    for side in bodies:
        for t0, t1 in _stance_off_plates(markers, contacts, side):
            exclude.append((t0, t1, f"{side} foot on the ground off the force plates (ground reaction unknown)"))
    return TrialLoads(tuple(loads), tuple(contacts), tuple(sorted(exclude)), tuple(notes))


def _lab_up(markers, notes: list) -> np.ndarray:
    """The trial's vertical read from its markers (`kinematics.gait.lab_frame.detect_lab`); +Z (the C3D
    convention) with a note when the markers do not tell it."""
    from kinematics.gait.lab_frame import detect_lab

    try:
        lab = detect_lab(None, [markers])
    except InputError as exc:
        notes.append(f"lab vertical not readable from the markers ({exc.problem}): +Z assumed")
        return np.array([0.0, 0.0, 1.0])
    notes.append(f"lab: {lab.describe()}")
    return np.asarray(lab.up, float)


def _stance_off_plates(markers, contacts, side: str, max_speed: float = 0.5, min_s: float = 0.05,
                       margin_s: float = 0.05) -> list[tuple[float, float]]:
    """Intervals where a foot stands (heel or toe slower than `max_speed`) without a usable plate contact.

    Foot-velocity stance detection (O'Connor et al. 2007): a standing foot
    has a marker at rest.  Intervals shorter than `min_s`, and the `margin_s`
    next to the foot's plate contacts (strike and push-off), are ignored.
    """
    from kinematics.gait.plate_contacts import foot_markers
    from kinematics.io.markers import true_runs

    names = foot_markers(markers, side)
    if "heel" not in names:
        return []
    t = markers.time
    speeds = []
    for role in ("heel", "toe"):
        if role in names:
            x = markers.marker(names[role])
            speeds.append(np.linalg.norm(np.gradient(x, t, axis=0), axis=1))
    with np.errstate(invalid="ignore"):
        stance = np.nanmin(np.vstack(speeds), axis=0) < max_speed
    covered = np.zeros(t.shape[0], bool)
    for c in contacts:
        if c.usable and c.foot == side:
            covered |= (t >= c.start_time - margin_s) & (t <= c.end_time + margin_s)
    out = []
    for a, b in true_runs(stance & ~covered):
        if t[b - 1] - t[a] >= min_s:
            out.append((float(t[a]), float(t[b - 1])))
    return out
