"""gait2392's leg muscles carried onto the personalised model's bodies.

Each muscle is a copy of the generic one (class, force-length-velocity properties, maximum isometric force,
pennation at optimal fibre length) whose path is re-expressed body by body through that body's
`bone_registration.BoneMap` (``x' = A x + t``, generic body frame -> personalised body frame, metres):

* ``PathPoint``: location mapped;
* ``ConditionalPathPoint``: location mapped, its coordinate renamed (``knee_angle`` -> ``knee_flexion``) and
  its active interval carried by the `poses.CoordinateMap` (``q_s = sign q_g + offset``);
* ``MovingPathPoint`` (gait2392's quadriceps insertions on the tibia, which stand in for the patella): the
  location curve ``x'(q_s) = A x(q_g(q_s)) + t`` sampled at `MOVING_SAMPLES` values over the generic functions'
  domain and refitted as one SimmSpline per axis of the subject's coordinate (an exact carry of the curve at
  the knots; between them a cubic spline of a smooth curve);
* wrap objects of the bodies (gait2392 has none; other generic models may): translation mapped, axes turned by
  the polar factor of ``A R``, radii and dimensions scaled by the stretch of ``A`` along the object's axes.

Optimal fibre and tendon slack lengths are then re-estimated (`calibration`).
"""
from __future__ import annotations

import numpy as np

__all__ = ["add_muscles", "MOVING_SAMPLES"]

#: samples of a moving path point's curve over its coordinate's domain
MOVING_SAMPLES = 25


def _vec(v) -> np.ndarray:
    return np.array([v.get(k) for k in range(3)], float)


def _rename_coordinate(path: str, cmap) -> tuple[str, str]:
    """Socket path of a generic coordinate -> (subject socket path, generic coordinate name)."""
    name = path.rstrip("/").rsplit("/", 1)[-1]
    joint = path.rstrip("/").rsplit("/", 2)[-2] if path.count("/") >= 2 else name.rsplit("_", 1)[0]
    sub = cmap.entries[name][0]
    return f"/jointset/{joint}/{sub}", name


def _moving(osim, mp, bmap, cmap) -> None:
    """Re-express a MovingPathPoint (module docstring)."""
    sockets = ("x_coordinate", "y_coordinate", "z_coordinate")
    funcs = (mp.get_x_location(), mp.get_y_location(), mp.get_z_location())
    paths = [mp.getSocket(s).getConnecteePath() for s in sockets]
    if len(set(paths)) != 1:
        raise ValueError(f"{mp.getName()}: the axes follow different coordinates")
    sub_path, gname = _rename_coordinate(paths[0], cmap)
    lo, hi = np.inf, -np.inf
    for f in funcs:
        sp = osim.SimmSpline.safeDownCast(f)
        if sp is not None and sp.getSize() >= 2:
            lo, hi = min(lo, sp.getX(0)), max(hi, sp.getX(sp.getSize() - 1))
    if not np.isfinite(lo):
        lo, hi = -np.pi, np.pi
    qg = np.linspace(lo, hi, MOVING_SAMPLES)
    X = np.array([[f.calcValue(osim.Vector(1, float(q))) for f in funcs] for q in qg])
    Xs = bmap(X)
    _, sign, off = cmap.entries[gname]
    qs = sign * qg + off
    order = np.argsort(qs)
    for k, (setter, s) in enumerate(((mp.set_x_location, sockets[0]), (mp.set_y_location, sockets[1]),
                                     (mp.set_z_location, sockets[2]))):
        spline = osim.SimmSpline()
        for q, v in zip(qs[order], Xs[order, k]):
            spline.addPoint(float(q), float(v))
        setter(spline)
        mp.updSocket(s).setConnecteePath(sub_path)


def _wrap_objects(osim, gbody, sbody, bmap) -> int:
    """Copy a generic body's wrap objects onto the subject's body through its map; returns how many."""
    ws = gbody.getWrapObjectSet()
    for k in range(ws.getSize()):
        w = ws.get(k).clone()
        from scipy.spatial.transform import Rotation

        xyz = _vec(w.get_xyz_body_rotation())
        R = Rotation.from_euler("XYZ", xyz).as_matrix()
        x = _vec(w.get_translation())
        Rn, stretch = bmap.frame(R, at=x)
        w.set_translation(osim.Vec3(*bmap(x)))
        w.set_xyz_body_rotation(osim.Vec3(*Rotation.from_matrix(Rn).as_euler("XYZ")))
        for cls, props in (("WrapCylinder", (("radius", (0, 1)), ("length", (2,)))),
                           ("WrapSphere", (("radius", (0, 1, 2)),)),
                           ("WrapTorus", (("inner_radius", (0, 1)), ("outer_radius", (0, 1)))),
                           ("WrapEllipsoid", ())):
            if w.getConcreteClassName() != cls:
                continue
            obj = getattr(osim, cls).safeDownCast(w)
            for prop, axes in props:
                f = float(np.mean(stretch[list(axes)]))
                getattr(obj, f"set_{prop}")(getattr(obj, f"get_{prop}")() * f)
            if cls == "WrapEllipsoid":
                obj.set_dimensions(osim.Vec3(*(_vec(obj.get_dimensions()) * stretch)))
        sbody.addWrapObject(w)
    return ws.getSize()


def add_muscles(om, generic, maps: dict, cmap, sides) -> dict:
    """Add the generic leg muscles of `sides` to the personalised opensim model `om` (not yet finalised).

    om : opensim.Model (the personalised model; same body names as gait2392's); generic : `GenericModel`;
    maps : body -> `BoneMap`; cmap : `poses.CoordinateMap`; sides : ('r', 'l') present

    Returns {"muscles": names added, "skipped": name -> reason, "wrap_objects": count}.
    """
    from kinematics.io.opensim_io import import_opensim

    osim = import_opensim()
    added, skipped, n_wrap = [], {}, 0
    bodies = om.getBodySet()
    for b, bmap in maps.items():
        if generic.model.getBodySet().contains(b) and bodies.contains(b):
            n_wrap += _wrap_objects(osim, generic.model.getBodySet().get(b), bodies.get(b), bmap)
    for gm in generic.muscles():
        name = gm.getName()
        if name.rsplit("_", 1)[-1] not in sides:
            continue
        mu = gm.clone()
        pps = mu.updGeometryPath().updPathPointSet()
        try:
            for j in range(pps.getSize()):
                p = pps.get(j)
                body = p.getSocket("parent_frame").getConnecteePath().rstrip("/").rsplit("/", 1)[-1]
                if body not in maps:
                    raise KeyError(f"body {body} has no map (no subject bone nor joint to place it)")
                mp = osim.MovingPathPoint.safeDownCast(p)
                if mp is not None:
                    _moving(osim, mp, maps[body], cmap)
                    continue
                pp = osim.PathPoint.safeDownCast(p)
                pp.set_location(osim.Vec3(*maps[body](_vec(pp.get_location()))))
                cp = osim.ConditionalPathPoint.safeDownCast(p)
                if cp is not None:
                    sub_path, gname = _rename_coordinate(cp.getSocket("coordinate").getConnecteePath(), cmap)
                    _, lo, hi = cmap.subject_range(gname, cp.get_range(0), cp.get_range(1))
                    cp.updSocket("coordinate").setConnecteePath(sub_path)
                    cp.set_range(0, lo)
                    cp.set_range(1, hi)
        except (KeyError, ValueError) as exc:
            skipped[name] = str(exc)
            continue
        om.addForce(mu)
        added.append(name)
    return {"muscles": added, "skipped": skipped, "wrap_objects": n_wrap}
