"""OpenSim interoperability: import .osim models into `Model`, export `Model` to .osim.

Import goes through the ``opensim`` API (which also upgrades OpenSim 3 files):
bodies with mass properties; CustomJoint SpatialTransforms with Constant,
LinearFunction, SimmSpline, MultiplierFunction (and order-1
MultivariatePolynomialFunction) functions; Pin, Slider, Universal, Gimbal,
Ball, Free, Planar and Weld joints (as the CustomJoint they are equivalent
to); CoordinateCouplerConstraints (linear ones become rows of the linear
coupling, others `CoordinateCoupler`); the MarkerSet; coordinate defaults,
ranges, locked and clamped flags.  The file is first checked with
``defusedxml`` so that a file that is not OpenSim XML gives a one-line
`InputError`.

Export builds an ``opensim.Model`` (every joint becomes a CustomJoint, or a
WeldJoint; linear coupling rows with one dependent coordinate become
CoordinateCouplerConstraints) and prints it.
"""
from __future__ import annotations

import os
from functools import lru_cache
from pathlib import Path

import numpy as np

from kinematics.multibody.coupling import CoordinateCoupler, LinearCoupling
from lowerlimb.errors import InputError
from kinematics.multibody.functions import Constant, Function, Linear, Multiplier, MultivariateLinear, NaturalCubicSpline, SimmSpline
from kinematics.multibody.joints import CustomJoint, Transform, TransformAxis, matrix_to_euler_xyz
from kinematics.multibody.model import GROUND, Body, Coordinate, Marker, Model

__all__ = ["degree_coordinates", "load_osim", "save_osim", "to_opensim", "check_osim_file", "read_xml", "import_opensim", "open_osim_model",
           "write_osim", "vec_from_opensim", "transform_from_opensim", "function_from_opensim", "function_to_opensim",
           "add_coupler_constraint", "opensim_inverse_kinematics", "run_opensim_ik_tool"]

_E = np.eye(3)

#: largest XML file read (bytes): the biggest published .osim models (full-body, muscles, meshes named) are under 10 MB
MAX_XML_BYTES = 50 * 1024 * 1024


def import_opensim():
    """The ``opensim`` module with its logger quietened to errors (`InputError` when it is not installed)."""
    try:
        import opensim
    except ImportError as exc:  # pragma: no cover - opensim is a dependency
        raise InputError(None, f"the opensim package is needed to read/write .osim files ({exc})") from None
    try:
        opensim.Logger.setLevel(opensim.Logger.Level_Error)
    except Exception:  # pragma: no cover - older bindings
        pass
    return opensim


_opensim = import_opensim        # former private name, kept for existing importers


@lru_cache(maxsize=None)
def polynomial_layout(k: int) -> tuple[int, ...]:
    """Input multiplied by each order-1 coefficient of OpenSim's MultivariatePolynomialFunction.

    Returns ``layout`` of length k: coefficient ``1 + j`` multiplies input
    ``layout[j]`` (coefficient 0 is the constant).  OpenSim 4.6 stores the
    order-1 terms with the inputs reversed; rather than assume it, the layout
    is probed by evaluating unit coefficient vectors at unit inputs.
    """
    osim = import_opensim()
    layout = []
    for j in range(k):
        f = osim.MultivariatePolynomialFunction()
        f.setDimension(k)
        f.setOrder(1)
        v = osim.Vector(k + 1, 0.0)
        v.set(j + 1, 1.0)
        f.setCoefficients(v)
        hits = []
        for i in range(k):
            x = osim.Vector(k, 0.0)
            x.set(i, 1.0)
            if abs(f.calcValue(x) - 1.0) < 1e-12:
                hits.append(i)
        if len(hits) != 1:
            raise RuntimeError(f"OpenSim MultivariatePolynomialFunction order-1 layout not understood (k={k})")
        layout.append(hits[0])
    if sorted(layout) != list(range(k)):
        raise RuntimeError("OpenSim MultivariatePolynomialFunction order-1 layout is not a permutation")
    return tuple(layout)


def read_xml(path: str | os.PathLike, missing: str, not_xml: str):
    """Root element of the XML file `path`, parsed with ``defusedxml``.

    Raises `InputError` naming `path`: `missing` when it is not a file,
    a file over `MAX_XML_BYTES` (refused before parsing), "refusing unsafe XML"
    for entity/DTD attacks, and ``f"{not_xml} ({exc})"`` when it is not
    well-formed XML.

    The file is parsed from one buffer: fed in the 64 KB chunks of
    ``ElementTree.parse``, expat < 2.6 re-scans a token longer than a chunk
    for every chunk (quadratic: a 5 MB attribute took 2.7 s, 0.5 s in one buffer).
    """
    from defusedxml import ElementTree as ET
    from defusedxml.common import DefusedXmlException

    path = Path(path)
    if not path.is_file():
        raise InputError(path, missing)
    try:
        size = path.stat().st_size
        if size > MAX_XML_BYTES:
            raise InputError(path, f"XML file of {size / 2**20:.0f} MB is over the {MAX_XML_BYTES / 2**20:.0f} MB "
                                   "bound for OpenSim files: refused before parsing")
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(path, f"cannot read ({exc.strerror or exc})") from None
    try:
        return ET.fromstring(data)
    except DefusedXmlException as exc:
        raise InputError(path, f"refusing unsafe XML ({type(exc).__name__})") from None
    except Exception as exc:
        raise InputError(path, f"{not_xml} ({exc})") from None


def check_osim_file(path: str | os.PathLike) -> None:
    """Raise `InputError` unless `path` is a readable OpenSim XML document with a Model."""
    path = Path(path)
    root = read_xml(path, "model file not found", "not an OpenSim model: the file is not XML")
    if root.tag != "OpenSimDocument" or root.find("Model") is None:
        raise InputError(path, f"not an OpenSim model: XML root is <{root.tag}>, expected <OpenSimDocument> with a <Model>")


def open_osim_model(path: str | os.PathLike):
    """Check `path` (`check_osim_file`) and load it as an initialised ``opensim.Model``.

    Raises `InputError` with OpenSim's first message line when OpenSim cannot load it.
    """
    check_osim_file(path)
    osim = import_opensim()
    try:
        om = osim.Model(os.fspath(path))
        om.finalizeFromProperties()
        om.initSystem()
    except Exception as exc:
        msg = str(exc).strip().splitlines()
        raise InputError(path, f"OpenSim cannot load the model: {msg[0] if msg else type(exc).__name__}") from None
    return om


def write_osim(om, path: str | os.PathLike) -> Path:
    """Print the ``opensim.Model`` `om` to `path` atomically (`InputError` when OpenSim refuses)."""
    from lowerlimb.atomic import atomic_path

    path = Path(path)
    with atomic_path(path) as tmp:
        if not om.printToXML(os.fspath(tmp)):
            raise InputError(path, "OpenSim could not write the model")
    return path


def vec_from_opensim(v) -> np.ndarray:
    """SimTK Vec3 -> (3,) float array."""
    return np.array([v.get(0), v.get(1), v.get(2)], dtype=float)


def transform_from_opensim(X) -> Transform:
    """SimTK Transform -> `Transform` (rotation re-orthonormalised)."""
    R = X.R()
    M = np.array([[R.get(i, j) for j in range(3)] for i in range(3)])
    # Re-orthonormalise (SimTK stores the rotation in double precision already; this only removes round-off).
    u, _, vt = np.linalg.svd(M)
    return Transform(u @ vt, vec_from_opensim(X.p()))


def function_from_opensim(osim, f, where: str, source) -> Function:
    """Convert an OpenSim Function to ours (`InputError` naming `source` and `where` for unsupported types)."""
    name = f.getConcreteClassName()
    if name == "Constant":
        return Constant(osim.Constant.safeDownCast(f).getValue())
    if name == "LinearFunction":
        lf = osim.LinearFunction.safeDownCast(f)
        return Linear(lf.getSlope(), lf.getIntercept())
    if name == "SimmSpline":
        s = osim.SimmSpline.safeDownCast(f)
        n = s.getSize()
        return SimmSpline([s.getX(i) for i in range(n)], [s.getY(i) for i in range(n)])
    if name == "NaturalCubicSpline":
        s = osim.NaturalCubicSpline.safeDownCast(f)
        n = s.getSize()
        return NaturalCubicSpline([s.getX(i) for i in range(n)], [s.getY(i) for i in range(n)])
    if name == "MultiplierFunction":
        mf = osim.MultiplierFunction.safeDownCast(f)
        return Multiplier(function_from_opensim(osim, mf.getFunction(), where, source), mf.getScale())
    if name == "MultivariatePolynomialFunction":
        mp = osim.MultivariatePolynomialFunction.safeDownCast(f)
        if mp.getOrder() == 1:
            c = [mp.getCoefficients().get(i) for i in range(mp.getCoefficients().size())]
            slopes = np.zeros(len(c) - 1)
            for j, i in enumerate(polynomial_layout(len(c) - 1)):
                slopes[i] = c[j + 1]
            return MultivariateLinear(slopes, c[0])
    raise InputError(source, f"{where}: unsupported OpenSim function type {name}")


# Former private names, kept for existing importers.
_vec, _transform, _function = vec_from_opensim, transform_from_opensim, function_from_opensim


def _coordinate(c, translational_only: frozenset = frozenset()) -> Coordinate:
    mt = c.getMotionType()
    kind = {1: "rotational", 2: "translational", 3: "coupled"}.get(int(mt), "rotational")
    if kind == "coupled":
        # OpenSim calls a coordinate "Coupled" when its axis function is not the identity
        # (gait2392's pelvis translations): its kind is that of the axes it drives
        kind = "translational" if c.getName() in translational_only else "rotational"
    return Coordinate(c.getName(), kind, c.getDefaultValue(), (c.getRangeMin(), c.getRangeMax()),
                      bool(c.getDefaultLocked()), bool(c.getDefaultClamped()))


_STANDARD = {
    # joint class -> (rotation axes, translation axes); coordinates feed the rotations first, in order
    # (checked against OpenSim's own FK in tests/test_kin_opensim.py)
    "PinJoint": ([_E[2]], []),
    "SliderJoint": ([], [_E[0]]),
    "UniversalJoint": ([_E[0], _E[1]], []),
    "GimbalJoint": ([_E[0], _E[1], _E[2]], []),
    "BallJoint": ([_E[0], _E[1], _E[2]], []),
    "FreeJoint": ([_E[0], _E[1], _E[2]], [_E[0], _E[1], _E[2]]),
    "PlanarJoint": ([_E[2]], [_E[0], _E[1]]),
    "WeldJoint": ([], []),
}


def degree_coordinates(model: Model) -> list[str]:
    """The coordinates an OpenSim storage with ``inDegrees=yes`` holds in degrees: those OpenSim calls Rotational,
    i.e. that drive a rotation axis through the identity function.  A coordinate driving its axes through other
    functions (a patella's, coupled to knee flexion through splines) is "Coupled" to OpenSim, which writes and
    reads it in radians whatever the header says; the other rotational coordinates are in degrees."""
    from kinematics.multibody.joints import is_identity_function

    rot = {c.name for c in model.coordinates if c.kind == "rotational"}
    identity = set()
    for j in model.joints:
        for ax in getattr(j, "rotations", ()):
            if is_identity_function(ax.function):
                identity.update(ax.coordinates)
    return [n for n in model.coordinate_names if n in rot and n in identity]


def load_osim(path: str | os.PathLike) -> Model:
    """Read an OpenSim model file into an immutable `Model`.

    Raises
    ------
    InputError
        Not OpenSim XML, unreadable by OpenSim, or using an unsupported joint,
        function or constraint type.
    """
    om = open_osim_model(path)
    return from_opensim(om, source=os.fspath(path))


def from_opensim(om, source=None) -> Model:
    """Convert an initialised ``opensim.Model`` to a `Model`."""
    osim = import_opensim()
    ground = om.getGround().getName()

    def base_name(frame) -> str:
        n = frame.findBaseFrame().getName()
        return GROUND if n == ground else n

    bodies = []
    bs = om.getBodySet()
    for i in range(bs.getSize()):
        b = bs.get(i)
        I = b.getInertia()
        mo, pr = vec_from_opensim(I.getMoments()), vec_from_opensim(I.getProducts())
        inertia = np.array([[mo[0], pr[0], pr[1]], [pr[0], mo[1], pr[2]], [pr[1], pr[2], mo[2]]])
        bodies.append(Body(b.getName(), b.getMass(), vec_from_opensim(b.getMassCenter()), inertia))
    joints, coords = [], []
    js = om.getJointSet()
    for i in range(js.getSize()):
        j = js.get(i)
        cls = j.getConcreteClassName()
        where = f"joint {j.getName()!r}"
        pf, cf = j.getParentFrame(), j.getChildFrame()
        po = transform_from_opensim(pf.findTransformInBaseFrame())
        co = transform_from_opensim(cf.findTransformInBaseFrame())
        jc = [j.get_coordinates(k) for k in range(j.numCoordinates())]
        cnames = tuple(c.getName() for c in jc)
        if cls == "CustomJoint":
            st = osim.CustomJoint.safeDownCast(j).getSpatialTransform()
            axes = []
            for k in range(6):
                ta = st.getTransformAxis(k)
                names = ta.getCoordinateNamesInArray()
                names = tuple(names.get(n) for n in range(names.getSize()))
                fn = function_from_opensim(osim, ta.getFunction(), f"{where} {ta.getName()}", source)
                if isinstance(fn, Constant) or (isinstance(fn, Multiplier) and isinstance(fn.function, Constant)):
                    names = ()
                    fn = Constant(fn(np.zeros((1, 0)))[0]) if isinstance(fn, Multiplier) else fn
                elif fn.n_inputs != len(names):
                    raise InputError(source, f"{where} {ta.getName()}: function of {fn.n_inputs} inputs on {len(names)} coordinates")
                axes.append(TransformAxis(vec_from_opensim(ta.getAxis()), fn, names))
            rotating = {n for ax in axes[:3] for n in ax.coordinates}
            translating = {n for ax in axes[3:] for n in ax.coordinates}
            coords.extend(_coordinate(c, frozenset(translating - rotating)) for c in jc)
            joints.append(CustomJoint(j.getName(), base_name(pf), base_name(cf), cnames, po, co,
                                      rotations=tuple(axes[:3]), translations=tuple(axes[3:]), kind_name="custom"))
        elif cls in _STANDARD:
            rot, tr = _STANDARD[cls]
            nr = len(rot)
            coords.extend(_coordinate(c, frozenset(cnames[nr:])) for c in jc)
            rots = tuple(TransformAxis(a, Linear(1.0, 0.0), (cnames[k],)) for k, a in enumerate(rot))
            trs = tuple(TransformAxis(a, Linear(1.0, 0.0), (cnames[nr + k],)) for k, a in enumerate(tr))
            joints.append(CustomJoint(j.getName(), base_name(pf), base_name(cf), cnames, po, co,
                                      rotations=rots, translations=trs, kind_name=cls.replace("Joint", "").lower()))
        else:
            raise InputError(source, f"{where}: unsupported joint type {cls}")
    couplings, couplers = None, []
    cs = om.getConstraintSet()
    cnames_all = tuple(c.name for c in coords)
    for i in range(cs.getSize()):
        c = cs.get(i)
        if not c.get_isEnforced():
            continue
        if c.getConcreteClassName() != "CoordinateCouplerConstraint":
            raise InputError(source, f"constraint {c.getName()!r}: unsupported constraint type {c.getConcreteClassName()}")
        cc = osim.CoordinateCouplerConstraint.safeDownCast(c)
        ind = cc.getIndependentCoordinateNames()
        ind = tuple(ind.get(k) for k in range(ind.getSize()))
        dep = cc.getDependentCoordinateName()
        fn = function_from_opensim(osim, cc.getFunction(), f"constraint {c.getName()!r}", source)
        try:
            sf = float(cc.getPropertyByName("scale_factor").toString())
        except Exception:  # pragma: no cover - property absent in old bindings
            sf = 1.0
        if sf != 1.0:
            # OpenSim couples q_dep = scale_factor * f(q_indep).
            if isinstance(fn, Linear):
                fn = Linear(sf * fn.slope, sf * fn.intercept)
            elif isinstance(fn, MultivariateLinear):
                fn = MultivariateLinear(sf * fn.coefficients, sf * fn.intercept)
            else:
                fn = Multiplier(fn, sf)
        if isinstance(fn, Linear) or isinstance(fn, MultivariateLinear):
            coef = [fn.slope] if isinstance(fn, Linear) else list(fn.coefficients)
            b = fn.intercept
            row = LinearCoupling.correlative(cnames_all, dep, dict(zip(ind, coef)), b)
            couplings = row if couplings is None else couplings.stack(row)
        else:
            couplers.append(CoordinateCoupler(dep, ind, fn, c.getName()))
    markers = []
    ms = om.getMarkerSet()
    for i in range(ms.getSize()):
        m = ms.get(i)
        pf = m.getParentFrame()
        X = transform_from_opensim(pf.findTransformInBaseFrame())
        markers.append(Marker(m.getName(), base_name(pf), X.apply(vec_from_opensim(m.get_location()))))
    g = vec_from_opensim(om.getGravity())
    try:
        return Model(tuple(bodies), tuple(joints), tuple(coords), tuple(markers), couplings=couplings,
                     couplers=tuple(couplers), gravity=g, name=om.getName())
    except ValueError as exc:
        raise InputError(source, f"inconsistent model: {exc}") from None


# ---------------------------------------------------------------------------------------- export
def function_to_opensim(osim, f: Function):
    """Build the OpenSim Function equal to `f` (Constant, Linear, SimmSpline, Multiplier, MultivariateLinear)."""
    if isinstance(f, Constant):
        return osim.Constant(float(f.value))
    if isinstance(f, Linear):
        return osim.LinearFunction(float(f.slope), float(f.intercept))
    if isinstance(f, SimmSpline):
        s = osim.SimmSpline()
        for x, y in zip(f.x, f.y):
            s.addPoint(float(x), float(y))
        return s
    if isinstance(f, Multiplier):
        inner = function_to_opensim(osim, f.function)
        # MultiplierFunction keeps the pointer: hand ownership to C++ so Python never frees it.
        inner.thisown = False
        return osim.MultiplierFunction(inner, float(f.scale))
    if isinstance(f, MultivariateLinear):
        mp = osim.MultivariatePolynomialFunction()
        mp.setDimension(f.n_inputs)
        mp.setOrder(1)
        v = osim.Vector(f.n_inputs + 1, 0.0)
        v.set(0, float(f.intercept))
        for j, i in enumerate(polynomial_layout(f.n_inputs)):
            v.set(j + 1, float(f.coefficients[i]))
        mp.setCoefficients(v)
        return mp
    raise InputError(None, f"cannot export function {type(f).__name__} to OpenSim")


def add_coupler_constraint(osim, om, name: str, dependent: str, independent, function) -> None:
    """Add a CoordinateCouplerConstraint ``dependent = function(independent...)`` to the ``opensim.Model`` `om`.

    `function` is an OpenSim Function; the constraint takes ownership of it.
    """
    cc = osim.CoordinateCouplerConstraint()
    cc.setName(name)
    cc.setDependentCoordinateName(dependent)
    arr = osim.ArrayStr()
    for n in independent:
        arr.append(n)
    cc.setIndependentCoordinateNames(arr)
    cc.setFunction(function)
    function.thisown = False           # the constraint keeps the pointer: keep Python from freeing it
    om.addConstraint(cc)


def _vec3(osim, v):
    v = np.asarray(v, float)
    return osim.Vec3(float(v[0]), float(v[1]), float(v[2]))


def to_opensim(model: Model):
    """Build an ``opensim.Model`` equivalent to `model` (not yet initialised)."""
    osim = import_opensim()
    om = osim.Model()
    om.setName(model.name)
    om.setGravity(_vec3(osim, model.gravity))
    obodies = {GROUND: om.getGround()}
    for b in model.bodies[1:]:
        I = b.inertia
        inertia = osim.Inertia(float(I[0, 0]), float(I[1, 1]), float(I[2, 2]), float(I[0, 1]), float(I[0, 2]), float(I[1, 2]))
        ob = osim.Body(b.name, float(b.mass), _vec3(osim, b.com), inertia)
        om.addBody(ob)
        obodies[b.name] = ob
    cdef = {c.name: c for c in model.coordinates}
    for j in model.joints:
        if not isinstance(j, CustomJoint):
            raise InputError(None, f"joint {j.name!r} ({j.kind}) has no OpenSim equivalent")
        po, co = j.parent_offset, j.child_offset
        args = (j.name, obodies[j.parent], _vec3(osim, po.translation), _vec3(osim, matrix_to_euler_xyz(po.rotation)),
                obodies[j.child], _vec3(osim, co.translation), _vec3(osim, matrix_to_euler_xyz(co.rotation)))
        if not j.coordinates:
            oj = osim.WeldJoint(*args)
        else:
            st = osim.SpatialTransform()
            for k in range(6):
                ta = st.updTransformAxis(k)
                axes = j.rotations if k < 3 else j.translations
                kk = k % 3
                if kk < len(axes):
                    ax = axes[kk]
                    names = osim.ArrayStr()
                    for n in ax.coordinates:
                        names.append(n)
                    ta.setCoordinateNames(names)
                    ta.setAxis(_vec3(osim, ax.axis))
                    ta.set_function(function_to_opensim(osim, ax.function))
                else:
                    # Unused axes: zero functions about axes completing an independent triad.
                    fill = _complete_axes([a.axis for a in axes])
                    ta.setAxis(_vec3(osim, fill[kk - len(axes)]))
                    ta.set_function(osim.Constant(0.0))
            oj = osim.CustomJoint(*args, st)
        om.addJoint(oj)
        for k, n in enumerate(j.coordinates):
            c = cdef[n]
            oc = oj.upd_coordinates(k)
            oc.setName(n)
            lo, hi = c.range
            # OpenSim refuses a default outside the range (a standing knee hyperextended past gait2392's -10 deg)
            oc.setDefaultValue(float(np.clip(c.default, lo, hi)))
            oc.setRangeMin(float(lo) if np.isfinite(lo) else -1e3)
            oc.setRangeMax(float(hi) if np.isfinite(hi) else 1e3)
            oc.setDefaultLocked(bool(c.locked))
            oc.setDefaultClamped(bool(c.clamped))
    if model.couplings is not None:
        names = model.couplings.coordinates
        for row, rhs, label in zip(model.couplings.matrix, model.couplings.rhs, model.couplings.labels):
            nz = np.flatnonzero(row)
            dep = label if label in names and row[names.index(label)] != 0 else names[nz[0]]
            a = row[names.index(dep)]
            ind = [names[i] for i in nz if names[i] != dep]
            coef = [-row[names.index(n)] / a for n in ind]
            f = Linear(coef[0], rhs / a) if len(ind) == 1 else MultivariateLinear(coef, rhs / a)
            add_coupler_constraint(osim, om, f"coupling_{dep}", dep, ind, function_to_opensim(osim, f))
    for cp in model.couplers:
        add_coupler_constraint(osim, om, cp.name or f"coupler_{cp.dependent}", cp.dependent, cp.independent,
                               function_to_opensim(osim, cp.function))
    for m in model.markers:
        om.addMarker(osim.Marker(m.name, obodies[m.body], _vec3(osim, m.offset)))
    om.finalizeConnections()
    return om


def _complete_axes(used):
    """Unit axes completing `used` (1 or 2 unit vectors) to an independent triad."""
    out = []
    basis = list(used)
    for e in _E:
        M = np.array(basis + [e])
        if np.linalg.matrix_rank(M, tol=1e-6) == len(M):
            basis.append(e)
            out.append(e)
        if len(basis) == 3:
            break
    return out


def save_osim(model: Model, path: str | os.PathLike) -> Path:
    """Export `model` to an OpenSim .osim file (written atomically)."""
    return write_osim(to_opensim(model), path)


def opensim_inverse_kinematics(model_path: str | os.PathLike, trc_path: str | os.PathLike,
                               marker_weights: dict | None = None, coordinate_tasks=(),
                               time_range: tuple[float, float] | None = None, accuracy: float = 1e-5):
    """Run OpenSim's own ``InverseKinematicsSolver`` (reference for tests and benchmarks).

    Returns
    -------
    dict with ``time`` (F,), ``q`` (F, n_q) SI in the model's coordinate order,
    ``coordinates``, ``markers``, ``marker_errors`` (F, M) m, ``rms`` (F,) m,
    ``seconds`` / ``cpu_seconds`` (wall / process time of the assemble + track loop only).
    """
    import time as _t

    osim = import_opensim()
    om = osim.Model(os.fspath(model_path))
    s = om.initSystem()
    ws = osim.SetMarkerWeights()
    for n, w in (marker_weights or {}).items():
        ws.cloneAndAppend(osim.MarkerWeight(n, float(w)))
    mref = osim.MarkersReference(os.fspath(trc_path), ws)
    cref = osim.SimTKArrayCoordinateReference()
    cs = om.getCoordinateSet()
    for t in coordinate_tasks:
        val = cs.get(t.name).getDefaultValue() if t.value is None else t.value
        r = osim.CoordinateReference(t.name, osim.Constant(float(val)))
        r.setWeight(float(t.weight))
        cref.push_back(r)
    solver = osim.InverseKinematicsSolver(om, mref, cref, float("inf"))
    solver.setAccuracy(float(accuracy))
    times = np.array(osim.TimeSeriesTableVec3(os.fspath(trc_path)).getIndependentColumn())
    if time_range is not None:
        times = times[(times >= time_range[0] - 1e-9) & (times <= time_range[1] + 1e-9)]
    names = [cs.get(i).getName() for i in range(cs.getSize())]
    Q = np.empty((times.size, len(names)))
    errs = []
    t0, c0 = _t.perf_counter(), _t.process_time()
    for k, t in enumerate(times):
        s.setTime(float(t))
        if k == 0:
            solver.assemble(s)
        else:
            solver.track(s)
        Q[k] = [cs.get(i).getValue(s) for i in range(len(names))]
        e = osim.SimTKArrayDouble()
        solver.computeCurrentMarkerErrors(e)
        errs.append([e.getElt(i) for i in range(e.size())])
    secs, cpu = _t.perf_counter() - t0, _t.process_time() - c0
    errs = np.array(errs, float)
    mnames = [solver.getMarkerNameForIndex(i) for i in range(errs.shape[1])]
    return {"time": times, "q": Q, "coordinates": names, "markers": mnames, "marker_errors": errs,
            "rms": np.sqrt(np.mean(errs**2, axis=1)), "seconds": secs, "cpu_seconds": cpu}


def run_opensim_ik_tool(setup_path: str | os.PathLike, results_directory: str | os.PathLike | None = None,
                        time_range: tuple[float, float] | None = None) -> dict:
    """Run OpenSim's ``InverseKinematicsTool`` on an IK setup file as OpenSim's GUI or ``opensim-cmd run-tool`` would.

    The setup's model, marker file and output names resolve against the setup's folder; with
    `results_directory` the output motion is written there instead, with `time_range` (s) only that window is
    solved (the setup file is not changed).

    Returns
    -------
    dict with ``time`` (F,), ``q`` (F, n_q) SI (rotations in rad) in the .mot's column order,
    ``coordinates`` and ``motion`` (the written .mot path).
    """
    from kinematics.io.storage import read_mot

    osim = import_opensim()
    setup_path = Path(setup_path).resolve()
    cwd = os.getcwd()
    try:
        os.chdir(setup_path.parent)              # OpenSim resolves relative names against the working directory
        tool = osim.InverseKinematicsTool(os.fspath(setup_path))
        if results_directory is not None:
            tool.set_results_directory(os.fspath(Path(results_directory).resolve()))
            Path(results_directory).mkdir(parents=True, exist_ok=True)
        out = Path(tool.getOutputMotionFileName())
        if results_directory is not None:
            out = Path(results_directory).resolve() / out.name
            tool.setOutputMotionFileName(os.fspath(out))
        if time_range is not None:
            tool.setStartTime(float(time_range[0]))
            tool.setEndTime(float(time_range[1]))
        if not tool.run():
            raise InputError(setup_path, "OpenSim's IK tool failed")
        out = out if out.is_absolute() else setup_path.parent / out
    finally:
        os.chdir(cwd)
    tab = read_mot(out)
    om = osim.Model(os.fspath((setup_path.parent / tool.get_model_file()).resolve()))
    cs = om.getCoordinateSet()
    rot = [cs.get(i).getName() for i in range(cs.getSize()) if int(cs.get(i).getMotionType()) == 1]
    tab = tab.to_radians([c for c in tab.columns if c in rot]) if tab.in_degrees else tab
    return {"time": np.asarray(tab.time, float), "q": np.asarray(tab.values, float), "coordinates": tuple(tab.columns),
            "motion": out}
