"""Ground reactions of a real-anatomy phantom's walk, written as C3D force platforms.

Model (lab frame, SI).  The whole body's linear momentum gives the total
ground reaction: ``F(t) = M (a_com(t) - g)`` with the centre of mass of the
truth model's bodies (`phantoms.real_subject.segment_bodies`) and ``g`` along
``-up``.  The trials keep the lowest foot point on the floor
(`phantoms.real_subject.on_the_floor`); a foot within `CONTACT_HEIGHT` of the
lower one is on it too.  A single foot on the floor takes the whole reaction;
over a double support the trailing foot hands it over smoothly
(`transfer_share`).  Each foot's centre of pressure is the mean of its hull
points within 3 mm of its lowest (heel first, rolling to the toes); the free
moment is taken as zero (the trunk's angular momentum is not modelled).

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


#: m, a foot whose lowest point is within this height of the lower foot's is on the floor too: the walk keeps
#: the lower foot on the floor, and at heel strike the leading heel lands while the trailing toe is still down
#: within 1-2 cm.  The phantom's walk then has only 2-4 frames (at 100 Hz) of double support per step against
#: walking's ~0.1 s: the load moves over in ~30 ms (the kinematics, not this split, are what keep the hip moments
#: above walking's)
CONTACT_HEIGHT = 0.015


def transfer_share(n: int) -> np.ndarray:
    """Share (n,) of the total reaction the trailing foot keeps over the n frames of a double support: the
    smooth-transition assumption of Ren, Jones & Howard (2008, J Biomech 41:2750), here a cubic step from 1 to 0
    (1 - 3τ² + 2τ³, τ = (i + 1) / (n + 1)): the leading foot takes the load gradually, not all of it at heel
    strike, where it would stand 30-40 cm ahead of the hip."""
    tau = (np.arange(n) + 1.0) / (n + 1.0)
    return 1.0 - tau ** 2 * (3.0 - 2.0 * tau)


def ground_reaction(anat, model, q: np.ndarray, rate: float, lab):
    """Total ground reaction of the whole body's momentum, split between the feet on the floor.

    Returns
    -------
    force : {"r", "l": (F, 3) N} lab, the reaction on each foot (0 in the air); cop : {side: (F, 3) m} lab, each
    foot's centre of pressure (its hull points within 3 mm of its lowest, on the floor); contact : {side: (F,)
    bool}.  A single foot on the floor takes the whole reaction; over a double support the trailing foot's share
    falls as `transfer_share`.
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
    total = M * (acc + 9.80665 * up)
    pts = {}
    for k, V in _foot_points(anat):
        side = model.body_names[k][-1]
        P = np.einsum("fij,pj->fpi", st.rotations[:, k], V) + st.positions[:, k][:, None]
        pts.setdefault(side, []).append(P)
    sides = sorted(pts)
    low, cop = {}, {}
    for s in sides:
        pts[s] = np.concatenate(pts[s], axis=1)
        h = pts[s] @ up
        low[s] = h.min(axis=1)
        near = h < low[s][:, None] + 0.003
        c = np.einsum("fp,fpi->fi", near, pts[s]) / near.sum(axis=1)[:, None]
        cop[s] = c - (c @ up)[:, None] * up[None]              # on the floor
    floor = np.min([low[s] for s in sides], axis=0)
    contact = {s: low[s] - floor < CONTACT_HEIGHT for s in sides}
    share = {s: contact[s].astype(float) for s in sides}
    if len(sides) == 2:
        stances = {s: _runs(contact[s]) for s in sides}
        for a, b in _runs(contact[sides[0]] & contact[sides[1]]):      # double support a .. b - 1
            # each foot's stance holding it: the trailing foot landed first (at the trial's start: it leaves first)
            key = {s: next((int(r0), int(r1)) for r0, r1 in stances[s] if r0 <= a < r1) for s in sides}
            trail = min(sides, key=key.get)
            lead = sides[1] if trail == sides[0] else sides[0]
            w = transfer_share(b - a)
            share[trail][a:b], share[lead][a:b] = w, 1.0 - w
    force = {s: share[s][:, None] * total for s in sides}
    return force, cop, contact


def _runs(on: np.ndarray) -> np.ndarray:
    """(first, end) frames (end exclusive), (n, 2), of the runs of True in the boolean series `on`."""
    d = np.diff(np.concatenate([[0], np.asarray(on, np.int8), [0]]))
    return np.column_stack([np.flatnonzero(d == 1), np.flatnonzero(d == -1)])


def stance_plates(cop: dict, contact: dict, lab, max_plates: int = 4):
    """Plates under the complete stance phases, in time order: list of (corners (4, 3) m, centre (3,), side,
    first, last frame)."""
    runs = sorted((int(a), int(b) - 1, str(side)) for side, on in contact.items() for a, b in _runs(on)
                  if a > 0 and b < len(on) and b - a >= 5)
    fwd = np.asarray(lab.forward, float)
    up = np.asarray(lab.up, float)
    left = np.cross(up, fwd)
    plates = []
    for a, b, side in runs[:max_plates]:
        c = cop[side][a:b + 1].mean(axis=0)
        hx, hy = PLATE_SIZE[0] / 2, PLATE_SIZE[1] / 2
        # c1..c4 such that X = c1 - c2 (forward) and Z = X x (c1 - c4) is up (kinematics.io.forceplates)
        corners = np.array([c + hx * fwd + hy * left, c - hx * fwd + hy * left,
                            c - hx * fwd - hy * left, c + hx * fwd - hy * left])
        plates.append((corners, c, side, a, b))
    return plates


def add_force_plates(c3d_path, force, cop, contact, lab, rate: float, *, max_plates: int = 4,
                     analog_per_frame: int = 10):
    """Add type-2 force platforms to the C3D at `c3d_path` (rewritten atomically), each carrying its foot's
    reaction over its stance (`ground_reaction`'s per-foot dicts); returns the plates' truth."""
    import ezc3d

    from lowerlimb.atomic import atomic_path

    plates = stance_plates(cop, contact, lab, max_plates)
    F = len(next(iter(contact.values())))
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
        f_lab = np.where(on[:, None], force[side], 0.0)
        p = np.where(on[:, None], cop[side], c)
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
