"""OpenSim export of correlative joints (Pronost et al. 2010, section 4.1).

Each dependent coordinate ``X = sum_i c_i Y_i + c0`` of a `CorrelativeLaw`
(seed eq. 2) becomes one OpenSim ``CoordinateCouplerConstraint`` whose
coupled-coordinates function is an order-1 ``MultivariatePolynomialFunction``
of the independent coordinates (a ``LinearFunction`` when there is one
independent), so that OpenSim 4.6 reproduces the correlative DOF in assembly,
IK and forward simulation.

OpenSim stores the order-1 coefficients as ``[c0, c_(k-1), ..., c_1, c_0']``
(the constant, then the inputs in *reverse* order; probed at run time by
`polynomial_layout` rather than assumed), so the functions are built and
checked here (`correlative_function` evaluates the OpenSim function against
the law before it is used).

* `export_correlative_model` writes an engine `Model` whose knee is
  correlative: the model goes through `kinematics.io.opensim_io.to_opensim`
  without the law's rows, and the constraints are added here.
* `add_correlative_constraints` adds the constraints to an existing
  ``opensim.Model`` (e.g. a user's gait2392) and `add_to_osim` does it to an
  .osim file.
* `verify_osim_law` loads the written file with OpenSim, sets the independent
  coordinates, assembles and measures how far the assembled dependent
  coordinates are from the law.

Every file is written atomically by OpenSim's ``printToXML`` (metres,
radians; frames as in the model).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from kinematics.mechanisms.correlative import CorrelativeLaw
from lowerlimb.errors import InputError
from kinematics.multibody.functions import Linear, MultivariateLinear
from kinematics.multibody.model import Model
from kinematics.io.opensim_io import (add_coupler_constraint, check_osim_file, function_to_opensim, import_opensim,
                         polynomial_layout, to_opensim, write_osim)

__all__ = ["polynomial_layout", "correlative_function", "add_correlative_constraints", "export_correlative_model",
           "add_to_osim", "OsimLawCheck", "verify_osim_law", "constraint_name"]


def constraint_name(dependent: str) -> str:
    """Name of the constraint that drives `dependent`."""
    return f"correlative_{dependent}"


def correlative_function(slopes: Sequence[float], intercept: float):
    """OpenSim function ``f(x) = intercept + sum_i slopes[i] x_i`` (x in the order of `slopes`), checked.

    One input: ``LinearFunction``; more: order-1 ``MultivariatePolynomialFunction``.
    """
    osim = import_opensim()
    c = np.asarray(slopes, float).ravel()
    k = c.size
    if k == 0:
        raise InputError(None, "a correlative DOF needs at least one independent coordinate")
    f = function_to_opensim(osim, Linear(float(c[0]), float(intercept)) if k == 1 else MultivariateLinear(c, intercept))
    # Self-check at a few points: the function OpenSim will evaluate equals the law.
    rng = np.random.default_rng(0)
    for x in rng.uniform(-1.5, 1.5, size=(3, k)):
        xv = osim.Vector(k, 0.0)
        for i in range(k):
            xv.set(i, float(x[i]))
        got = f.calcValue(xv)
        want = float(intercept + c @ x)
        if abs(got - want) > 1e-12 * max(1.0, abs(want)):
            raise RuntimeError(f"OpenSim function evaluates {got} instead of {want}")
    return f


def add_correlative_constraints(om, laws: Sequence[CorrelativeLaw], replace: bool = True, source=None) -> list[str]:
    """Add one CoordinateCouplerConstraint per dependent coordinate of each law to ``opensim.Model`` `om`.

    The dependent coordinates are unlocked (OpenSim cannot drive a locked
    coordinate); with `replace`, enforced CoordinateCouplerConstraints that
    already drive one of them are removed first.  Returns the constraint names.

    Raises
    ------
    InputError
        A law names a coordinate the model lacks, or a coordinate is driven twice.
    """
    osim = import_opensim()
    cs = om.getCoordinateSet()
    have = {cs.get(i).getName() for i in range(cs.getSize())}
    deps = [d for law in laws for d in law.dependent]
    if len(set(deps)) != len(deps):
        raise InputError(source, f"a coordinate is the dependent of two laws ({deps})")
    for law in laws:
        missing = [n for n in law.independent + law.dependent if n not in have]
        if missing:
            raise InputError(source, f"law {law.joint!r}: the OpenSim model has no coordinate {', '.join(missing)}")
        bad = [n for n in law.independent if n in deps]
        if bad:
            raise InputError(source, f"law {law.joint!r}: independent coordinate(s) {bad} are driven by another law")
    con = om.updConstraintSet()
    for i in reversed(range(con.getSize())):
        c = con.get(i)
        if c.getConcreteClassName() != "CoordinateCouplerConstraint":
            continue
        dep = osim.CoordinateCouplerConstraint.safeDownCast(c).getDependentCoordinateName()
        if dep in deps:
            if not replace:
                raise InputError(source, f"coordinate {dep!r} is already driven by constraint {c.getName()!r}")
            con.remove(i)
    names = []
    for law in laws:
        for dep, ind, slopes, c0 in law.as_linear_forms():
            add_coupler_constraint(osim, om, constraint_name(dep), dep, ind, correlative_function(slopes, c0))
            cs.get(dep).setDefaultLocked(False)
            names.append(constraint_name(dep))
    # Default pose on the laws, so that the file's defaults already satisfy them.
    for law in laws:
        a = np.array([cs.get(n).getDefaultValue() for n in law.independent])
        for n, v in zip(law.dependent, law.predict(a)):
            cs.get(n).setDefaultValue(float(v))
    om.finalizeConnections()
    return names


def export_correlative_model(model: Model, laws: Sequence[CorrelativeLaw], path: str | os.PathLike) -> Path:
    """Write `model` to .osim with the correlative `laws` as CoordinateCouplerConstraints.

    Coupling rows and couplers of `model` that drive a law's dependent
    coordinates are dropped (the laws replace them); the rest of the model goes
    through `kinematics.io.opensim_io.to_opensim`.
    """
    deps = {d for law in laws for d in law.dependent}
    for law in laws:
        for n in law.independent + law.dependent:
            try:
                model.coordinate_index(n)
            except KeyError:
                raise InputError(os.fspath(path), f"law {law.joint!r}: model {model.name!r} has no coordinate {n!r}") from None
    cp = None if model.couplings is None else model.couplings.without(deps)
    couplers = tuple(c for c in model.couplers if c.dependent not in deps)
    om = to_opensim(model.replace(couplings=cp, couplers=couplers))
    add_correlative_constraints(om, laws, source=os.fspath(path))
    return write_osim(om, path)


def add_to_osim(src: str | os.PathLike, laws: Sequence[CorrelativeLaw], out: str | os.PathLike) -> Path:
    """Read the OpenSim model `src`, add the correlative constraints, write `out` (atomically)."""
    check_osim_file(src)
    osim = import_opensim()
    try:
        om = osim.Model(os.fspath(src))
    except Exception as exc:
        raise InputError(src, f"OpenSim cannot load the model ({str(exc).splitlines()[0] if str(exc) else exc})") from None
    add_correlative_constraints(om, laws, source=os.fspath(src))
    return write_osim(om, out)


@dataclass(frozen=True)
class OsimLawCheck:
    """Assembled OpenSim poses against the laws.

    max_law_error : max over poses and dependents of |X_assembled - law(Y_assembled)| (m or rad)
    max_independent_shift : max |Y_assembled - Y_set| (how much assembly moved the independents)
    max_dependent_correction : max |X_assembled - X_before| (assembly did move the dependents)
    n_poses : poses checked
    constraints : names of the enforced correlative constraints found in the file
    """

    max_law_error: float
    max_independent_shift: float
    max_dependent_correction: float
    n_poses: int
    constraints: tuple[str, ...]


def verify_osim_law(path: str | os.PathLike, laws: Sequence[CorrelativeLaw], poses=None, n_poses: int = 5,
                    seed: int = 0) -> OsimLawCheck:
    """Load `path` in OpenSim, pose the independents, assemble, and compare the dependents to the laws.

    Parameters
    ----------
    poses : array (n_poses, sum_k) of independent values (the laws' independents concatenated), optional
        Default: uniform draws over +-0.3 of each coordinate's range around its default
        (seeded by `seed`); the dependents start 5 mm / 0.05 rad off the law.
    """
    osim = import_opensim()
    om = osim.Model(os.fspath(path))
    state = om.initSystem()
    cs = om.getCoordinateSet()
    cons = om.getConstraintSet()
    found = tuple(cons.get(i).getName() for i in range(cons.getSize())
                  if cons.get(i).getConcreteClassName() == "CoordinateCouplerConstraint" and cons.get(i).get_isEnforced())
    ind = [n for law in laws for n in law.independent]
    if poses is None:
        rng = np.random.default_rng(seed)
        lo = np.array([cs.get(n).getRangeMin() for n in ind])
        hi = np.array([cs.get(n).getRangeMax() for n in ind])
        d0 = np.array([cs.get(n).getDefaultValue() for n in ind])
        span = np.clip(hi - lo, 0, 2.0)
        poses = np.clip(d0 + 0.3 * span * rng.uniform(-1, 1, size=(n_poses, len(ind))), lo, hi)
    poses = np.atleast_2d(np.asarray(poses, float))
    err = shift = corr = 0.0
    for p in poses:
        k = 0
        for law in laws:
            for n in law.independent:
                cs.get(n).setValue(state, float(p[k]), False)
                k += 1
            for n in law.dependent:
                c = cs.get(n)
                off = 0.005 if c.getMotionType() == osim.Coordinate.Translational else 0.05
                c.setValue(state, c.getValue(state) + off, False)
        before = {n: cs.get(n).getValue(state) for law in laws for n in law.dependent}
        om.assemble(state)
        k = 0
        for law in laws:
            y = np.array([cs.get(n).getValue(state) for n in law.independent])
            shift = max(shift, float(np.max(np.abs(y - p[k:k + len(y)]))))
            k += len(y)
            x = np.array([cs.get(n).getValue(state) for n in law.dependent])
            err = max(err, float(np.max(np.abs(x - law.predict(y)))))
            corr = max(corr, float(np.max(np.abs(x - np.array([before[n] for n in law.dependent])))))
    return OsimLawCheck(err, shift, corr, len(poses), found)
