r"""Plug-in-Gait lower-limb kinetics (Vicon Nexus' conventions): joint moments and powers.

Bottom-up Newton-Euler through foot, tibia and femur of each leg, on the
segment frames and joint centres of `kinematics.gait.pig`, with the ground reaction
of the force plate the foot stands on applied at its centre of pressure.

Segment inertial parameters (Dempster 1955, as Plug-in-Gait uses them), with
M the body mass and L the segment length::

    segment   mass / M   centre of mass                                   radius of gyration / L
    foot      0.0145     mid-point of ankle centre and toe marker            0.475
    tibia     0.0465     0.567 L from the ankle centre towards the knee      0.302
    femur     0.100      0.567 L from the knee centre towards the hip        0.323

(the centre of mass 0.433 L from the proximal joint), inertia about the
centre of mass :math:`I = \mathrm{diag}(m (\rho L)^2, m (\rho L)^2, 0)` in the
segment frame (x, y transverse, z the long axis).

Equations per segment, distal to proximal (lab frame, moments about the lab origin):

.. math::

    F_p = m (a_c - g) - F_d, \qquad
    M_p = c \times m (a_c - g) + R (I \dot\omega_l + \omega_l \times I \omega_l) - M_d,

where :math:`(F_d, M_d)` is the wrench on the segment at its distal end (the
ground reaction :math:`(F, p \times F + T)` for the foot; minus the proximal
wrench of the segment below otherwise), :math:`c` and :math:`a_c` the centre
of mass and its acceleration, :math:`\omega_l` the angular velocity in the
segment frame (from :math:`\dot R R^T`).  The joint moment is the moment the
proximal segment exerts on the distal one about the joint centre j,
:math:`M_j = M_p - j \times F_p`, expressed in the distal segment's frame (as
Nexus' default "distal" output), and reported in Plug-in-Gait's component
order and signs (internal moments; x sagittal, y frontal, z transverse)::

    joint   X (sagittal)          Y (frontal)               Z (transverse)
    hip     +M_y  extensor +      -M_x (R) / +M_x (L)        -M_z (R) / +M_z (L)
    knee    -M_y  extensor +      -M_x (R) / +M_x (L)        -M_z (R) / +M_z (L)
    ankle   +M_y  plantarflexor + +M_z (R) / -M_z (L)        -M_x (R) / +M_x (L)

(M_x, M_y, M_z in the distal frame; the foot's z runs toe-to-ankle, its x up).
Joint power :math:`P = M_j \cdot (\omega_{distal} - \omega_{proximal})` (W).
Velocities and accelerations are central differences of the trajectories
(optionally low-passed first by `kinematics.gait.filtering.lowpass`; Nexus filters
markers in its pipeline, before the model).

Frames where a foot is on the ground but on no usable plate (slower than
``contact_speed`` with no load assigned) have no valid moments at that leg:
they are NaN, never computed without the missing ground reaction.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lowerlimb.errors import InputError
from kinematics.io.markers import MarkerTrial
from kinematics.gait.pig import PiGResult

__all__ = [
    "PIG_SEGMENTS",
    "GroundReaction",
    "PiGKinetics",
    "SegmentInertia",
    "angular_velocity",
    "ground_reactions",
    "pig_components",
    "plug_in_gait_kinetics",
]

GRAVITY = np.array([0.0, 0.0, -9.81])  # m/s², C3D lab frames (Z up)


@dataclass(frozen=True)
class SegmentInertia:
    """Dempster parameters: mass fraction of body mass, centre of mass fraction of the
    length from the distal joint (the foot: from the ankle centre to the toe marker), radius of
    gyration about the centre of mass as a fraction of the length."""

    mass_fraction: float
    com_fraction: float
    gyration: float


PIG_SEGMENTS = {"foot": SegmentInertia(0.0145, 0.5, 0.475),
                "tibia": SegmentInertia(0.0465, 0.567, 0.302),
                "femur": SegmentInertia(0.100, 0.567, 0.323)}

# Plug-in-Gait output component k = sign * M_local[index] (right side; the left flips Y and Z).
_PIG_COMPONENTS = {"hip": ((1, +1), (0, -1), (2, -1)),
                   "knee": ((1, -1), (0, -1), (2, -1)),
                   "ankle": ((1, +1), (2, +1), (0, -1))}


@dataclass(frozen=True)
class GroundReaction:
    """Ground reaction on one foot over a trial (lab frame, SI).

    force : (F, 3) N; cop : (F, 3) m (NaN where unloaded); free_moment : (F, 3) N m;
    loaded : (F,) bool; plates : tuple of (plate index, start, stop) applied
    """

    force: np.ndarray
    cop: np.ndarray
    free_moment: np.ndarray
    loaded: np.ndarray
    plates: tuple = ()


@dataclass(frozen=True)
class PiGKinetics:
    """Plug-in-Gait kinetics of both legs.

    Attributes
    ----------
    moments : dict ``hip_r, knee_r, ankle_r, ..._l`` -> (F, 3) N m, Plug-in-Gait components
        (sagittal, frontal, transverse; see module docstring), in the distal segment's frame
    forces : dict same keys -> (F, 3) N, force of the proximal on the distal segment, lab frame
    powers : dict same keys -> (F,) W
    mass : float, kg
    grf : dict ``R``/``L`` -> GroundReaction applied
    valid : dict ``R``/``L`` -> (F,) bool, frames whose ground reaction is known
    time : (F,) s
    notes : tuple of str
    """

    moments: dict
    forces: dict
    powers: dict
    mass: float
    grf: dict
    valid: dict
    time: np.ndarray
    notes: tuple = field(default_factory=tuple)

    def moment_per_kg(self, name: str, unit: str = "N m/kg") -> np.ndarray:
        """Moment `name` per kg of body mass, in ``"N m/kg"`` or ``"N mm/kg"`` (Nexus' unit)."""
        scale = {"N m/kg": 1.0, "N mm/kg": 1e3}[unit]
        return self.moments[name] * scale / self.mass

    def power_per_kg(self, name: str) -> np.ndarray:
        """Power `name` in W/kg (Nexus' unit)."""
        return self.powers[name] / self.mass


def angular_velocity(axes: np.ndarray, rate: float) -> np.ndarray:
    """Angular velocity (F, 3) rad/s in the lab frame of rotations `axes` (F, 3, 3), from Ṙ Rᵀ."""
    Rd = np.gradient(axes, 1.0 / rate, axis=0)
    W = np.einsum("fij,fkj->fik", Rd, axes)
    return 0.5 * np.stack([W[:, 2, 1] - W[:, 1, 2], W[:, 0, 2] - W[:, 2, 0], W[:, 1, 0] - W[:, 0, 1]], -1)


def pig_components(moment_local: np.ndarray, joint: str, side: str) -> np.ndarray:
    """Reorder and sign a distal-frame moment (F, 3) into Plug-in-Gait's (X, Y, Z) components."""
    out = np.empty_like(moment_local)
    for k, (j, sign) in enumerate(_PIG_COMPONENTS[joint]):
        mirror = -1.0 if (side == "L" and k > 0) else 1.0
        out[:, k] = sign * mirror * moment_local[:, j]
    return out


def ground_reactions(plates, contacts, n_frames: int) -> tuple[dict, list[str]]:
    """Per-foot ground reactions from force plates and their foot assignment.

    Parameters
    ----------
    plates : kinematics.io.forceplates.ForcePlates, sampled at the marker frames
    contacts : list of kinematics.gait.plate_contacts.PlateContact (from `assign_feet`)
    n_frames : int, number of marker frames

    Returns
    -------
    grf : dict ``R``/``L`` -> GroundReaction (zero force off the plates)
    notes : list of str, one per loaded interval not applied (no single foot, CoP outside...)
    """
    if plates.n_frames != n_frames:
        raise InputError(plates.source, f"force plates have {plates.n_frames} frames, the markers {n_frames}: "
                                        "read the plates at the point frames")
    grf, notes = {}, []
    for side in "RL":
        f = np.zeros((n_frames, 3))
        M = np.zeros((n_frames, 3))        # moment about the lab origin, summed over plates
        wcop = np.zeros((n_frames, 3))     # centres of pressure weighted by each plate's normal force
        w = np.zeros(n_frames)
        loaded = np.zeros(n_frames, bool)
        used = []
        for c in contacts:
            if c.foot != side:
                continue
            if not c.usable:
                notes.append(f"{side} foot: {c.describe()} not applied")
                continue
            p = plates[c.plate]
            sl = slice(c.start, c.stop)
            if loaded[sl].any():
                notes.append(f"{side} foot on two plates at once (plate {c.plate + 1}): their wrenches are summed")
            ok = p.loaded[sl] & np.all(np.isfinite(p.cop[sl]), axis=1)
            fi = np.where(ok[:, None], p.force[sl], 0.0)
            ci = np.where(ok[:, None], p.cop[sl], 0.0)
            f[sl] += fi
            M[sl] += np.cross(ci, fi) + np.where(ok[:, None], p.free_moment[sl], 0.0)
            wi = np.abs(fi @ p.normal)
            wcop[sl] += wi[:, None] * ci
            w[sl] += wi
            loaded[sl] |= ok
            used.append((c.plate, c.start, c.stop))
        # one plate: cop and free moment as measured; two: the force-weighted cop with the torque that keeps
        # the summed wrench exact (M = cop x F + T)
        cop = np.full((n_frames, 3), np.nan)
        cop[loaded] = wcop[loaded] / w[loaded, None]
        T = np.zeros((n_frames, 3))
        T[loaded] = M[loaded] - np.cross(cop[loaded], f[loaded])
        grf[side] = GroundReaction(f, cop, T, loaded, tuple(used))
    for c in contacts:
        if c.foot is None:
            notes.append(f"{c.describe()}: not applied to either foot")
    return grf, notes


def _lowpass(x, rate, cutoff):
    if cutoff is None:
        return x
    from kinematics.gait.filtering import lowpass

    return lowpass(x, rate, cutoff)


def plug_in_gait_kinetics(trial: MarkerTrial, pig: PiGResult, mass: float, grf: dict, *,
                          cutoff: float | None = None, contact_speed: float = 0.3,
                          segments: dict = PIG_SEGMENTS) -> PiGKinetics:
    """Plug-in-Gait hip, knee and ankle moments, joint forces and powers of both legs.

    Parameters
    ----------
    trial : MarkerTrial, the dynamic trial (m), with the toe markers
    pig : PiGResult of `kinematics.gait.pig.plug_in_gait` on `trial` (calibrated feet)
    mass : float, kg, body mass (VSK ``Bodymass``)
    grf : dict ``R``/``L`` -> GroundReaction (see `ground_reactions`)
    cutoff : float, Hz, optional low-pass of centres and axes before differentiation
    contact_speed : float, m/s; a foot slower than this (mean heel/toe speed) and not loaded is
        taken as standing off the plates: its leg's moments are NaN there
    segments : dict of SegmentInertia

    Returns
    -------
    PiGKinetics
    """
    if mass is None or not (np.isfinite(mass) and mass > 0):
        raise InputError(trial.source, f"body mass must be a positive number of kg (VSK Bodymass), got {mass}")
    if "foot_r" not in pig.segments or "foot_l" not in pig.segments:
        raise InputError(trial.source, "feet not calibrated (run static_foot_offsets): no ankle kinetics")
    rate = trial.rate
    dt = 1.0 / rate
    notes = []
    moments, forces, powers, valid = {}, {}, {}, {}
    omegas = {"pelvis": angular_velocity(_lowpass(pig.segments["pelvis"].axes, rate, cutoff), rate)}
    for side, sfx in (("R", "_r"), ("L", "_l")):
        C = pig.centres
        toe = trial.marker(f"{side}TOE")
        chain = (("ankle", "foot", C["ankle" + sfx], toe),
                 ("knee", "tibia", C["knee" + sfx], C["ankle" + sfx]),
                 ("hip", "femur", C["hip" + sfx], C["knee" + sfx]))
        g = grf[side]
        cop = np.where(np.isfinite(g.cop), g.cop, 0.0)
        Fd, Md = g.force, np.cross(cop, g.force) + g.free_moment
        for joint, seg, prox, dist in chain:
            p = segments[seg]
            m = p.mass_fraction * mass
            L = np.linalg.norm(prox - dist, axis=1)
            com = prox + p.com_fraction * (dist - prox) if seg == "foot" else dist + p.com_fraction * (prox - dist)
            com = _lowpass(com, rate, cutoff)
            acc = np.gradient(np.gradient(com, dt, axis=0), dt, axis=0)
            R = _lowpass(pig.segments[seg + sfx].axes, rate, cutoff)
            w = angular_velocity(R, rate)
            omegas[seg + sfx] = w
            wd = np.gradient(w, dt, axis=0)
            I = m * (p.gyration * L) ** 2
            Iloc = np.stack([I, I, np.zeros_like(I)], -1)
            wl = np.einsum("fji,fj->fi", R, w)
            wdl = np.einsum("fji,fj->fi", R, wd)
            H = np.einsum("fij,fj->fi", R, Iloc * wdl + np.cross(wl, Iloc * wl))
            ma = m * (acc - GRAVITY)
            Fp = ma - Fd
            Mp = np.cross(com, ma) + H - Md
            Mj = Mp - np.cross(prox, Fp)
            name = joint + sfx
            moments[name] = pig_components(np.einsum("fji,fj->fi", pig.segments[seg + sfx].axes, Mj), joint, side)
            forces[name] = Fp
            powers[name] = Mj
            Fd, Md = -Fp, -Mp
        for joint, prox_seg, dist_seg in (("ankle", "tibia", "foot"), ("knee", "femur", "tibia"), ("hip", "pelvis", "femur")):
            name = joint + sfx
            wp = omegas[prox_seg if prox_seg == "pelvis" else prox_seg + sfx]
            powers[name] = np.sum(powers[name] * (omegas[dist_seg + sfx] - wp), axis=1)
        # a foot standing still off the plates: its ground reaction is unknown
        speed = 0.5 * sum(np.linalg.norm(np.gradient(trial.marker(f"{side}{mk}"), dt, axis=0), axis=1)
                          for mk in ("HEE", "TOE")) if f"{side}HEE" in trial.names else \
            np.linalg.norm(np.gradient(toe, dt, axis=0), axis=1)
        with np.errstate(invalid="ignore"):
            off_plate = (speed < contact_speed) & ~g.loaded
        valid[side] = ~off_plate
        if off_plate.any():
            notes.append(f"{side} foot on the ground off the plates in {int(off_plate.sum())} frames: "
                         "its leg's moments and powers are NaN there")
        for joint in ("ankle", "knee", "hip"):
            moments[joint + sfx] = np.where(off_plate[:, None], np.nan, moments[joint + sfx])
            forces[joint + sfx] = np.where(off_plate[:, None], np.nan, forces[joint + sfx])
            powers[joint + sfx] = np.where(off_plate, np.nan, powers[joint + sfx])
    return PiGKinetics(moments, forces, powers, float(mass), grf, valid, trial.time, tuple(notes))
