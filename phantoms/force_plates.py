"""Ground reactions of a real-anatomy phantom's walk, written as C3D force platforms.

Model (lab frame, SI).  The whole body's linear momentum gives the total
ground reaction: ``F(t) = M (a_com(t) - g)`` with the centre of mass of the
truth model's bodies (`phantoms.real_subject.segment_bodies`) and ``g`` along
``-up``.  The trials keep the lowest foot point on the floor
(`phantoms.real_subject.on_the_floor`), so at any frame one foot is on it;
that foot takes the whole reaction.  Its centre of pressure is the mean of its
hull points within 3 mm of the floor (heel first, rolling to the toes); the
free moment is taken as zero (the trunk's angular momentum is not modelled).

Plates: one 0.5 x 0.4 m plate (long side along the walk, surface at floor
level) centred under each complete stance phase (at most `max_plates`),
stances that start or end with the trial left off, as a gait lab places
plates so that whole strikes land on them.  Channels are type-2 (Fx Fy Fz
Mx My Mz: the reaction on the subject, N and N mm, about the surface centre,
plate axes = X forward, Y to the left, Z up) at 10 x the point rate.
"""
from __future__ import annotations

import numpy as np

__all__ = ["ground_reaction", "stance_plates", "add_force_plates"]

PLATE_SIZE = (0.5, 0.4)          # m, along the walk x across


def ground_reaction(anat, model, q: np.ndarray, rate: float, lab):
    """Total ground reaction and the foot that carries it.

    Returns
    -------
    force : (F, 3) N, lab; cop : (F, 3) m, lab; foot : (F,) array of "r"/"l"
    """
    from .real_subject import _fk, _foot_points

    st = _fk(model, q)
    M = sum(b.mass for b in model.bodies)
    com = np.zeros((q.shape[0], 3))
    for k, b in enumerate(model.bodies):
        if b.mass > 0:
            com += b.mass * (np.einsum("fij,j->fi", st.rotations[:, k], b.com) + st.positions[:, k])
    com /= M
    dt = 1.0 / rate
    acc = np.gradient(np.gradient(com, dt, axis=0), dt, axis=0)
    up = np.asarray(lab.up, float)
    force = M * (acc + 9.80665 * up)
    low, pts = {}, {}
    for k, V in _foot_points(anat):
        side = model.body_names[k][-1]
        P = np.einsum("fij,pj->fpi", st.rotations[:, k], V) + st.positions[:, k][:, None]
        pts.setdefault(side, []).append(P)
    cop = np.zeros_like(com)
    for s in pts:
        pts[s] = np.concatenate(pts[s], axis=1)
        low[s] = (pts[s] @ up).min(axis=1)
    sides = sorted(pts)
    foot = np.array([min(sides, key=lambda s: low[s][f]) for f in range(q.shape[0])])
    for f in range(q.shape[0]):
        P = pts[foot[f]][f]
        h = P @ up
        near = P[h < h.min() + 0.003]
        c = near.mean(axis=0)
        cop[f] = c - (c @ up) * up               # on the floor
    return force, cop, foot


def stance_plates(cop: np.ndarray, foot: np.ndarray, lab, max_plates: int = 4):
    """Plates under the complete stance phases: list of (corners (4, 3) m, centre (3,), side, first, last)."""
    F = len(foot)
    runs = []
    a = 0
    for f in range(1, F + 1):
        if f == F or foot[f] != foot[a]:
            if a > 0 and f < F and f - a >= 5:
                runs.append((a, f - 1, str(foot[a])))
            a = f
    fwd = np.asarray(lab.forward, float)
    up = np.asarray(lab.up, float)
    left = np.cross(up, fwd)
    plates = []
    for a, b, side in runs[:max_plates]:
        c = cop[a:b + 1].mean(axis=0)
        hx, hy = PLATE_SIZE[0] / 2, PLATE_SIZE[1] / 2
        # c1..c4 such that X = c1 - c2 (forward) and Z = X x (c1 - c4) is up (kinematics.io.forceplates)
        corners = np.array([c + hx * fwd + hy * left, c - hx * fwd + hy * left,
                            c - hx * fwd - hy * left, c + hx * fwd - hy * left])
        plates.append((corners, c, side, a, b))
    return plates


def add_force_plates(c3d_path, force, cop, foot, lab, rate: float, *, max_plates: int = 4, analog_per_frame: int = 10):
    """Add type-2 force platforms to the C3D at `c3d_path` (rewritten atomically); returns the plates' truth."""
    import ezc3d

    from lowerlimb.atomic import atomic_path

    plates = stance_plates(cop, foot, lab, max_plates)
    F = force.shape[0]
    fwd, up = np.asarray(lab.forward, float), np.asarray(lab.up, float)
    R = np.column_stack([fwd, np.cross(up, fwd), up])            # plate axes in the lab
    n_an = F * analog_per_frame
    t_pt = np.arange(F)
    t_an = np.arange(n_an) / analog_per_frame
    channels = np.zeros((6 * len(plates), n_an))
    truth = []
    for i, (corners, c, side, a, b) in enumerate(plates):
        on = np.zeros(F, bool)
        on[a:b + 1] = True
        f_lab = np.where(on[:, None], force, 0.0)
        p = np.where(on[:, None], cop, c)
        m_lab = np.cross(p - c, f_lab)                           # about the surface centre, free moment 0
        f_pl, m_pl = f_lab @ R, m_lab @ R
        for j in range(3):
            channels[6 * i + j] = np.interp(t_an, t_pt, f_pl[:, j])
            channels[6 * i + 3 + j] = np.interp(t_an, t_pt, m_pl[:, j]) * 1e3      # N mm
        truth.append({"plate": i + 1, "foot": side, "frames": [int(a), int(b)], "centre_m": c.tolist(),
                      "corners_m": corners.tolist()})
    c = ezc3d.c3d(str(c3d_path))
    labels = [f"{n}{i + 1}" for i in range(len(plates)) for n in ("Fx", "Fy", "Fz", "Mx", "My", "Mz")]
    c["parameters"]["ANALOG"]["RATE"]["value"] = [float(rate * analog_per_frame)]
    c["parameters"]["ANALOG"]["LABELS"]["value"] = labels
    c["parameters"]["ANALOG"]["USED"]["value"] = [len(labels)]
    c["parameters"]["ANALOG"]["SCALE"]["value"] = [1.0] * len(labels)
    c["parameters"]["ANALOG"]["OFFSET"]["value"] = [0] * len(labels)
    c["parameters"]["ANALOG"]["UNITS"]["value"] = ["N", "N", "N", "Nmm", "Nmm", "Nmm"] * len(plates)
    c.add_parameter("FORCE_PLATFORM", "USED", [len(plates)])
    c.add_parameter("FORCE_PLATFORM", "TYPE", [2] * len(plates))
    c.add_parameter("FORCE_PLATFORM", "ZERO", [1, 0])
    corners_mm = np.stack([p[0].T * 1e3 for p in plates], axis=2) if plates else np.zeros((3, 4, 0))
    c.add_parameter("FORCE_PLATFORM", "CORNERS", corners_mm.tolist())
    c.add_parameter("FORCE_PLATFORM", "ORIGIN", np.zeros((3, len(plates))).tolist())
    c.add_parameter("FORCE_PLATFORM", "CHANNEL", (np.arange(6 * len(plates)).reshape(len(plates), 6).T + 1).tolist())
    c["data"]["analogs"] = channels[None]
    with atomic_path(c3d_path) as tmp:
        c.write(str(tmp))
    return truth
