"""Inverse dynamics of a whole trial: filtered coordinates, ground reactions, joint moments and powers.

For the coordinates q_k at times t_k (an IK result), the pipeline is

1. low-pass q (`kinematics.filtering.lowpass`; by default OpenSim's
   InverseDynamicsTool filter: N/2 reflected padding, 3rd-order Butterworth
   forward and backward at the cut-off),
2. an interpolating natural quintic spline through the filtered samples
   (padding included, as OpenSim's GCVSplineSet) gives q, qd, qdd at t_k,
3. each external load (force F, point p, free torque T, ground frame) is
   interpolated at t_k by a natural cubic spline (OpenSim's ExternalForce
   uses an interpolating cubic GCV spline) and applied to its body as the
   wrench (F, T + (p - o_b) x F) at the body origin o_b,
4. the generalised forces follow from the transmission chain
   (`kinematics.dynamics.inverse_dynamics`, Taendl et al. eq. 24):

       tau = M(q) qdd + C(q, qd) qd - G(q) - sum_loads J_b(q)^T w_b

   and the joint powers P = tau * qd (W; N m x rad/s or N x m/s).

Moments are N m for rotational coordinates, N for translational ones (the
"*_moment" / "*_force" columns of OpenSim's output), in the model's
coordinate directions; ``per_kg`` divides by the model's mass.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .dynamics import inverse_dynamics
from .errors import InputError
from .external_loads import ExternalLoad
from .filtering import DEFAULT_CUTOFF_HZ, _opensim_lowpass, lowpass
from .model import Model
from .transmission import AppliedLoad, TransmissionChain

__all__ = ["InverseDynamicsResult", "coordinate_kinds", "trial_inverse_dynamics", "write_inverse_dynamics",
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


def coordinate_kinds(model: Model) -> tuple[str, ...]:
    """``rotational`` / ``translational`` per coordinate, from the joints' axes.

    A coordinate that drives only translation axes of a CustomJoint is
    translational even when the model reader called it rotational (OpenSim
    reports such coordinates as "Coupled" when their axis function is not the
    identity, e.g. gait2392's pelvis translations).
    """
    trans, rot = set(), set()
    for j in model.joints:
        for ax in getattr(j, "translations", ()) or ():
            trans.update(ax.coordinates)
        for ax in getattr(j, "rotations", ()) or ():
            rot.update(ax.coordinates)
    out = []
    for c in model.coordinates:
        if c.name in trans and c.name not in rot:
            out.append("translational")
        elif c.name in rot and c.name not in trans:
            out.append("rotational")
        else:
            out.append(c.kind if c.kind in ("rotational", "translational") else "rotational")
    return tuple(out)


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
        `kinematics.filtering.lowpass` method.
    load_cutoff : float or None, Hz
        Low-pass the loads' force and moment about the ground origin (same
        zero-lag filter) before use; None keeps them as given (OpenSim's tool).
    start, end : float, s
        Output window (the whole filtered trial is used for the splines).

    Returns
    -------
    InverseDynamicsResult
    """
    from .filtering import derivatives

    t = np.asarray(time, float).ravel()
    q = np.asarray(q, float)
    n = model.n_q
    if q.ndim != 2 or q.shape != (t.shape[0], n):
        raise InputError("coordinates", f"array of shape {q.shape} for {t.shape[0]} times x {n} model coordinates")
    if t.shape[0] < 6:
        raise InputError("coordinates", "at least 6 frames are needed")
    dt = np.diff(t)
    if np.any(dt <= 0) or (dt.max() - dt.min()) > 1e-3 * dt.mean():
        raise InputError("coordinates", "times must be uniformly sampled and increasing")
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
    if loads:
        from .fk import forward_kinematics

        pos = forward_kinematics(model, qf).positions
        for ld in loads:
            try:
                b = model.body_index(ld.body)
            except Exception:  # noqa: BLE001 - model lookups raise their own error types
                raise InputError(ld.name, f"load applied to body {ld.body!r}, which the model does not have") from None
            F, P, T = ld.force, ld.point, ld.torque
            M = np.cross(P, F) + T  # moment about the ground origin: continuous through contact changes
            if load_cutoff is not None and load_cutoff > 0:
                lr = 1.0 / np.mean(np.diff(ld.time))
                F = lowpass(F, lr, load_cutoff, source=ld.name)
                M = lowpass(M, lr, load_cutoff, source=ld.name)
            FM = _interp_cubic(ld.time, np.hstack([F, M]), t)
            Fk, Mk = FM[:, :3], FM[:, 3:]
            outside = (t < ld.time[0] - 1e-9) | (t > ld.time[-1] + 1e-9)
            if outside.any():
                Fk[outside] = 0.0
                Mk[outside] = 0.0
                notes.append(f"{ld.name}: no load data for {int(outside.sum())} frames (taken as no load)")
            ob = pos[:, b]
            applied.append(AppliedLoad(ld.body, Fk, np.zeros((t.shape[0], 3)), Mk - np.cross(ob, Fk)))
            bodies.append(ld.body)
        if load_cutoff:
            notes.append(f"loads low-pass filtered at {load_cutoff:g} Hz")
    else:
        notes.append("no external loads: kinematics-driven moments only (no ground reactions)")
    tau = inverse_dynamics(model, qf, qd, qdd, applied, chain=ch)
    return InverseDynamicsResult(tuple(model.coordinate_names), coordinate_kinds(model), t, qf, qd, qdd, tau,
                                 tau * qd, model.total_mass, tuple(bodies), tuple(notes))


def write_inverse_dynamics(path, result: InverseDynamicsResult, per_kg: bool = False) -> Path:
    """Write generalised forces as OpenSim's InverseDynamicsTool does (``*_moment`` / ``*_force`` columns)."""
    from .storage import write_sto

    vals = result.tau_per_kg if per_kg else result.tau
    unit = "N m/kg (rotational), N/kg (translational)" if per_kg else "N m (rotational), N (translational)"
    return write_sto(path, result.labels, result.time, vals, name="Inverse Dynamics",
                     header_extra=[f"Generalized forces in {unit}, along the model's coordinates;",
                                   f"model mass {result.mass:.3f} kg"])


def write_joint_powers(path, result: InverseDynamicsResult, per_kg: bool = False) -> Path:
    """Joint powers tau * qd (W or W/kg), one ``<coordinate>_power`` column per coordinate."""
    from .storage import write_sto

    vals = result.power_per_kg if per_kg else result.power
    return write_sto(path, [f"{c}_power" for c in result.coordinates], result.time, vals, name="Joint powers",
                     header_extra=[f"Joint powers tau * qd in {'W/kg' if per_kg else 'W'};",
                                   f"model mass {result.mass:.3f} kg"])
