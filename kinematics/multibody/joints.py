"""Joints: the motion of a child frame M relative to a parent frame F.

Each joint connects a frame F fixed on the parent body (``parent_offset``,
the pose of F in the parent body frame) to a frame M fixed on the child body
(``child_offset``, the pose of M in the child body frame), exactly like
OpenSim's two PhysicalOffsetFrames.  A joint reads the generalized
coordinates named in ``coordinates`` (columns of ``qj``) and returns, for N
samples at once,

* ``transform(qj)``: X_FM = (R_FM (N,3,3), p_FM (N,3)), the pose of M in F;
* ``motion_subspace(qj)``: S (N,6,k), with the spatial velocity of M relative
  to F, expressed in F, equal to ``S @ qdj``: rows 0-2 angular velocity,
  rows 3-5 velocity of M's origin;
* ``motion_subspace_derivative(qj, qdj)``: dS/dt (N,6,k), so that the
  relative spatial acceleration is ``S qdd + dS/dt qd`` (for dynamics).

The workhorse is :class:`CustomJoint` (OpenSim's CustomJoint /
SpatialTransform, Simbody's FunctionBased mobilizer): three rotations
theta_i = f_i(q) about axes a_i applied in sequence (each about the axis
carried by the previous rotations, R_FM = R(a1,theta1) R(a2,theta2) R(a3,theta3))
followed by translations p_FM = sum_j t_j(q) b_j along axes fixed in F.
Weld, revolute (pin), prismatic (slider), universal, spherical with any
Bryant/Cardan sequence and free joints are CustomJoints with identity
functions.  :class:`SwingJoint` (exponential map without twist) and
:class:`ExpMapSpherical` (rotation vector, singularity-free away from
|r| = 2 pi) are separate.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from kinematics.multibody.functions import Constant, Function, Linear, read_only
from lowerlimb.geometry import skew

__all__ = [
    "Transform", "TransformAxis", "Joint", "CustomJoint", "SwingJoint", "ExpMapSpherical",
    "weld", "revolute", "prismatic", "universal", "spherical", "free",
    "rotation_about", "euler_to_matrix", "matrix_to_euler_xyz", "exp_so3", "left_jacobian_so3",
    "left_jacobian_inverse_so3", "is_identity_function",
]


def rotation_about(axis: np.ndarray, angle) -> np.ndarray:
    """Rodrigues rotation matrices about a fixed unit `axis` by `angle` (N,) -> (N,3,3)."""
    a = np.asarray(axis, dtype=float)
    a = a / np.linalg.norm(a)
    angle = np.asarray(angle, dtype=float)
    K = skew(a)
    c, s = np.cos(angle)[..., None, None], np.sin(angle)[..., None, None]
    return np.eye(3) + s * K + (1.0 - c) * (K @ K)


def euler_to_matrix(angles, sequence: str = "XYZ") -> np.ndarray:
    """Body-fixed (intrinsic) rotation R = R_a1(q1) R_a2(q2) R_a3(q3), angles (...,3) radians."""
    angles = np.asarray(angles, dtype=float)
    R = np.broadcast_to(np.eye(3), angles.shape[:-1] + (3, 3)).copy()
    for i, ax in enumerate(sequence.upper()):
        R = R @ rotation_about(np.eye(3)["XYZ".index(ax)], angles[..., i])
    return R


def matrix_to_euler_xyz(R: np.ndarray) -> np.ndarray:
    """Inverse of ``euler_to_matrix(., 'XYZ')`` (OpenSim's ``orientation`` convention), shape (..., 3).

    R = Rx(a) Ry(b) Rz(c) gives R02 = sin b, R12 = -sin a cos b, R22 = cos a cos b,
    R01 = -cos b sin c, R00 = cos b cos c (b in [-pi/2, pi/2]; at gimbal lock c = 0).
    """
    R = np.asarray(R, dtype=float)
    b = np.arcsin(np.clip(R[..., 0, 2], -1.0, 1.0))
    lock = np.abs(R[..., 0, 2]) > 1.0 - 1e-12
    a = np.where(lock, np.arctan2(R[..., 2, 1], R[..., 1, 1]), np.arctan2(-R[..., 1, 2], R[..., 2, 2]))
    c = np.where(lock, 0.0, np.arctan2(-R[..., 0, 1], R[..., 0, 0]))
    return np.stack([a, b, c], axis=-1)


def exp_so3(r: np.ndarray) -> np.ndarray:
    """Rotation matrices exp([r]x) of rotation vectors r (N,3)."""
    r = np.asarray(r, dtype=float)
    th = np.linalg.norm(r, axis=-1)[..., None, None]
    K = skew(r)
    small = th < 1e-8
    ths = np.where(small, 1.0, th)
    A = np.where(small, 1.0 - th**2 / 6.0, np.sin(ths) / ths)
    B = np.where(small, 0.5 - th**2 / 24.0, (1.0 - np.cos(ths)) / ths**2)
    return np.eye(3) + A * K + B * (K @ K)


def left_jacobian_so3(r: np.ndarray) -> np.ndarray:
    """Left Jacobian J(r) of SO(3): d/dt exp([r]) = [J(r) dr/dt]x exp([r]), shape (N,3,3)."""
    r = np.asarray(r, dtype=float)
    th = np.linalg.norm(r, axis=-1)[..., None, None]
    K = skew(r)
    small = th < 1e-6
    ths = np.where(small, 1.0, th)
    B = np.where(small, 0.5 - th**2 / 24.0, (1.0 - np.cos(ths)) / ths**2)
    C = np.where(small, 1.0 / 6.0 - th**2 / 120.0, (ths - np.sin(ths)) / ths**3)
    return np.eye(3) + B * K + C * (K @ K)


def left_jacobian_inverse_so3(r: np.ndarray) -> np.ndarray:
    """Inverse J(r)^-1 of the SO(3) left Jacobian (closed form), shape (N,3,3).

    J^-1 = I - [r]x / 2 + (1/th^2 - (1 + cos th) / (2 th sin th)) [r]x^2, th = |r| (series 1/12 near 0).
    """
    r = np.asarray(r, dtype=float)
    th = np.linalg.norm(r, axis=-1)[..., None, None]
    K = skew(r)
    small = th < 1e-6
    ths = np.where(small, 1.0, th)
    c = np.where(small, 1.0 / 12.0, 1.0 / ths**2 - (1.0 + np.cos(ths)) / (2.0 * ths * np.sin(ths)))
    return np.eye(3) - 0.5 * K + c * (K @ K)


@dataclass(frozen=True, eq=False)
class Transform:
    """Rigid transform x_parent = rotation @ x_local + translation (metres)."""

    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))
    _identity: bool = field(default=False, init=False, repr=False, compare=False)

    def __post_init__(self):
        R = np.asarray(self.rotation, dtype=float)
        p = np.asarray(self.translation, dtype=float)
        if R.shape != (3, 3) or p.shape != (3,):
            raise ValueError("Transform needs a 3x3 rotation and a 3-vector translation")
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-9) or np.linalg.det(R) < 0:
            raise ValueError("Transform rotation is not a proper rotation matrix")
        object.__setattr__(self, "rotation", read_only(R))
        object.__setattr__(self, "translation", read_only(p))
        object.__setattr__(self, "_identity", bool(np.array_equal(R, np.eye(3)) and not p.any()))

    @classmethod
    def from_euler_xyz(cls, orientation=(0, 0, 0), translation=(0, 0, 0)) -> "Transform":
        """OpenSim offset frame: body-fixed X-Y-Z ``orientation`` (rad) and ``translation`` (m)."""
        return cls(euler_to_matrix(np.asarray(orientation, float), "XYZ"), translation)

    def inverse(self) -> "Transform":
        return Transform(self.rotation.T, -self.rotation.T @ self.translation)

    def __matmul__(self, other: "Transform") -> "Transform":
        return Transform(self.rotation @ other.rotation, self.rotation @ other.translation + self.translation)

    def apply(self, x) -> np.ndarray:
        return np.asarray(x, float) @ self.rotation.T + self.translation

    @property
    def is_identity(self) -> bool:
        return self._identity


@dataclass(frozen=True, eq=False)
class Joint:
    """Base joint; see the module docstring for the conventions.

    Attributes
    ----------
    name : str
    parent, child : str
        Body names (``"ground"`` for the ground).
    coordinates : tuple of str
        Coordinates read by the joint, in the column order of ``qj``.
    parent_offset : Transform
        Pose of the joint frame F in the parent body frame.
    child_offset : Transform
        Pose of the joint frame M in the child body frame.
    """

    name: str
    parent: str
    child: str
    coordinates: tuple[str, ...] = ()
    parent_offset: Transform = field(default_factory=Transform)
    child_offset: Transform = field(default_factory=Transform)

    kind = "joint"

    @property
    def n_coordinates(self) -> int:
        return len(self.coordinates)

    def _qj(self, qj) -> np.ndarray:
        qj = np.asarray(qj, dtype=float)
        if qj.ndim == 1:
            qj = qj[None, :]
        if qj.shape[1] != self.n_coordinates:
            raise ValueError(f"joint {self.name!r} reads {self.n_coordinates} coordinates, got {qj.shape[1]}")
        return qj

    def transform(self, qj) -> tuple[np.ndarray, np.ndarray]:
        """Pose of M in F: R_FM (N,3,3), p_FM (N,3)."""
        R, p, _ = self.motion_subspace(qj)
        return R, p

    def motion_subspace(self, qj) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """R_FM (N,3,3), p_FM (N,3) and S (N,6,k): [omega; v_M] in F per unit qdj."""
        raise NotImplementedError

    def motion_subspace_derivative(self, qj, qdj) -> np.ndarray:
        """dS/dt (N,6,k) along the velocity qdj (central difference of S along qdj)."""
        qj = self._qj(qj)
        qdj = np.broadcast_to(np.asarray(qdj, float), qj.shape)
        h = 1e-6
        Sp = self.motion_subspace(qj + h * qdj)[2]
        Sm = self.motion_subspace(qj - h * qdj)[2]
        return (Sp - Sm) / (2 * h)


@dataclass(frozen=True, eq=False)
class TransformAxis:
    """One axis of a SpatialTransform: a function of some coordinates along/about `axis`."""

    axis: np.ndarray
    function: Function = field(default_factory=lambda: Constant(0.0))
    coordinates: tuple[str, ...] = ()

    def __post_init__(self):
        a = np.asarray(self.axis, dtype=float)
        n = np.linalg.norm(a)
        if a.shape != (3,) or n == 0:
            raise ValueError("TransformAxis needs a non-zero 3-vector axis")
        object.__setattr__(self, "axis", read_only(a / n))
        object.__setattr__(self, "coordinates", tuple(self.coordinates))
        if self.function.n_inputs != len(self.coordinates):
            # Constant functions ignore their inputs (OpenSim lists coordinates anyway).
            if isinstance(self.function, Constant) or (hasattr(self.function, "function") and isinstance(self.function.function, Constant)):
                object.__setattr__(self, "coordinates", ())
            else:
                raise ValueError(f"function of {self.function.n_inputs} inputs on an axis listing {len(self.coordinates)} coordinates")


_I3 = np.eye(3)
_I3.setflags(write=False)


def is_identity_function(f: Function) -> bool:
    """f(q) = q exactly (identity linear function)."""
    return type(f) is Linear and f.slope == 1.0 and f.intercept == 0.0


@dataclass(frozen=True, eq=False)
class CustomJoint(Joint):
    """OpenSim CustomJoint: 3 rotation axes then 3 translation axes, each a function of coordinates.

    R_FM = R(a1, f1(q)) R(a2, f2(q)) R(a3, f3(q)),   p_FM = sum_j g_j(q) b_j.

    ``rotations`` and ``translations`` hold up to three `TransformAxis` each
    (missing ones are zero).  ``coordinates`` defaults to the union of the
    axes' coordinates in order of appearance.
    """

    rotations: tuple[TransformAxis, ...] = ()
    translations: tuple[TransformAxis, ...] = ()
    kind_name: str = "custom"
    _rot_cols: tuple = field(default=(), init=False, repr=False, compare=False)
    _tr_cols: tuple = field(default=(), init=False, repr=False, compare=False)
    _rot_ops: tuple = field(default=(), init=False, repr=False, compare=False)
    _tr_ops: tuple = field(default=(), init=False, repr=False, compare=False)

    def __post_init__(self):
        object.__setattr__(self, "rotations", tuple(self.rotations))
        object.__setattr__(self, "translations", tuple(self.translations))
        if len(self.rotations) > 3 or len(self.translations) > 3:
            raise ValueError("a CustomJoint has at most 3 rotation and 3 translation axes")
        names = list(self.coordinates)
        if not names:
            for ax in self.rotations + self.translations:
                for c in ax.coordinates:
                    if c not in names:
                        names.append(c)
        object.__setattr__(self, "coordinates", tuple(names))
        for ax in self.rotations + self.translations:
            for c in ax.coordinates:
                if c not in names:
                    raise ValueError(f"joint {self.name!r}: axis reads coordinate {c!r} not listed in the joint's coordinates")
        idx = lambda ax: np.array([names.index(c) for c in ax.coordinates], dtype=int)
        object.__setattr__(self, "_rot_cols", tuple(idx(a) for a in self.rotations))
        object.__setattr__(self, "_tr_cols", tuple(idx(a) for a in self.translations))
        # Pre-computed evaluation plan (speed: FK runs thousands of times in IK).
        rot_ops = []
        for ax, c in zip(self.rotations, self._rot_cols):
            Kx = skew(ax.axis)
            if c.size == 0:
                ang = float(ax.function.evaluate(np.zeros((1, 0)), order=0)[0][0])
                if ang != 0.0:
                    rot_ops.append((ax, c, Kx, Kx @ Kx, rotation_about(ax.axis, ang)))
            else:
                rot_ops.append((ax, c, Kx, Kx @ Kx, None))
        tr_ops = []
        for ax, c in zip(self.translations, self._tr_cols):
            if c.size == 0:
                v = float(ax.function.evaluate(np.zeros((1, 0)), order=0)[0][0])
                if v != 0.0:
                    tr_ops.append((ax, c, v * ax.axis))
            else:
                tr_ops.append((ax, c, None))
        object.__setattr__(self, "_rot_ops", tuple(rot_ops))
        object.__setattr__(self, "_tr_ops", tuple(tr_ops))

    @property
    def kind(self) -> str:  # type: ignore[override]
        return self.kind_name

    def _eval_axes(self, qj, axes, cols, order):
        N, k = qj.shape
        vals, grads, hess = [], [], []
        for ax, c in zip(axes, cols):
            out = ax.function.evaluate(qj[:, c], order=order)
            vals.append(out[0])
            if order >= 1:
                g = np.zeros((N, k))
                g[:, c] = out[1]
                grads.append(g)
            if order >= 2:
                H = np.zeros((N, k, k))
                H[:, c[:, None], c[None, :]] = out[2]
                hess.append(H)
        return vals, grads, hess

    def motion_subspace(self, qj):
        qj = self._qj(qj)
        N, k = qj.shape
        R = None                                   # None: identity so far
        S = np.zeros((N, 6, k))
        for ax, c, Kx, Kx2, Rc in self._rot_ops:
            if Rc is not None:                     # constant rotation
                R = Rc if R is None else R @ Rc
                continue
            u = ax.axis if R is None else R @ ax.axis          # current axis expressed in F
            if is_identity_function(ax.function):              # theta = q: the common case
                val = qj[:, c[0]]
                S[:, :3, c[0]] += u
            else:
                val, grad = ax.function.evaluate(qj[:, c], order=1)
                for j, cj in enumerate(c):
                    S[:, :3, cj] += u * grad[:, j, None]
            sn, cs = np.sin(val)[:, None, None], np.cos(val)[:, None, None]
            Rt = _I3 + sn * Kx + (1.0 - cs) * Kx2
            R = Rt if R is None else R @ Rt
        if R is None:
            R = np.broadcast_to(np.eye(3), (N, 3, 3))
        elif R.ndim == 2:
            R = np.broadcast_to(R, (N, 3, 3))
        p = np.zeros((N, 3))
        for ax, c, pc in self._tr_ops:
            if pc is not None:
                p += pc
                continue
            if is_identity_function(ax.function):
                p += qj[:, c[0], None] * ax.axis
                S[:, 3:, c[0]] += ax.axis
                continue
            val, grad = ax.function.evaluate(qj[:, c], order=1)
            p += val[:, None] * ax.axis
            for j, cj in enumerate(c):
                S[:, 3:, cj] += ax.axis * grad[:, j, None]
        return R, p, S

    def motion_subspace_derivative(self, qj, qdj) -> np.ndarray:
        qj = self._qj(qj)
        N, k = qj.shape
        qdj = np.broadcast_to(np.asarray(qdj, float), qj.shape)
        th, gr, hr = self._eval_axes(qj, self.rotations, self._rot_cols, 2)
        _, _, ht = self._eval_axes(qj, self.translations, self._tr_cols, 2)
        R = np.broadcast_to(np.eye(3), (N, 3, 3)).copy()
        w = np.zeros((N, 3))                      # angular velocity of the axes so far
        Sd = np.zeros((N, 6, k))
        for ax, t, g, H in zip(self.rotations, th, gr, hr):
            u = R @ ax.axis
            ud = np.cross(w, u)
            gd = np.einsum("nij,nj->ni", H, qdj)
            Sd[:, :3, :] += ud[:, :, None] * g[:, None, :] + u[:, :, None] * gd[:, None, :]
            w = w + u * np.einsum("ni,ni->n", g, qdj)[:, None]
            R = R @ rotation_about(ax.axis, t)
        for ax, H in zip(self.translations, ht):
            gd = np.einsum("nij,nj->ni", H, qdj)
            Sd[:, 3:, :] += ax.axis[None, :, None] * gd[:, None, :]
        return Sd


def _axes(coords, axes):
    return tuple(TransformAxis(a, Linear(1.0, 0.0), (c,)) for c, a in zip(coords, axes))


_E = np.eye(3)


def weld(name, parent, child, parent_offset=None, child_offset=None) -> CustomJoint:
    """Rigid connection (no coordinates)."""
    return CustomJoint(name, parent, child, (), parent_offset or Transform(), child_offset or Transform(), kind_name="weld")


def revolute(name, parent, child, coordinate, axis=(0, 0, 1), parent_offset=None, child_offset=None) -> CustomJoint:
    """Rotation by q about `axis` of F (OpenSim PinJoint: axis Z)."""
    return CustomJoint(name, parent, child, (coordinate,), parent_offset or Transform(), child_offset or Transform(),
                       rotations=_axes([coordinate], [axis]), kind_name="revolute")


def prismatic(name, parent, child, coordinate, axis=(1, 0, 0), parent_offset=None, child_offset=None) -> CustomJoint:
    """Translation by q along `axis` of F (OpenSim SliderJoint: axis X)."""
    return CustomJoint(name, parent, child, (coordinate,), parent_offset or Transform(), child_offset or Transform(),
                       translations=_axes([coordinate], [axis]), kind_name="prismatic")


def universal(name, parent, child, coordinates, axes=((1, 0, 0), (0, 1, 0)), parent_offset=None, child_offset=None) -> CustomJoint:
    """Two rotations about axes[0] then the carried axes[1] (OpenSim UniversalJoint: X then Y)."""
    return CustomJoint(name, parent, child, tuple(coordinates), parent_offset or Transform(), child_offset or Transform(),
                       rotations=_axes(coordinates, axes), kind_name="universal")


def spherical(name, parent, child, coordinates, sequence="XYZ", parent_offset=None, child_offset=None) -> CustomJoint:
    """Three body-fixed rotations in the Bryant/Cardan `sequence` (e.g. 'XYZ', 'ZXY'); also proper Euler ('ZXZ')."""
    axes = [_E["XYZ".index(s)] for s in sequence.upper()]
    return CustomJoint(name, parent, child, tuple(coordinates), parent_offset or Transform(), child_offset or Transform(),
                       rotations=_axes(coordinates, axes), kind_name="spherical")


def free(name, parent, child, coordinates, sequence="XYZ", parent_offset=None, child_offset=None) -> CustomJoint:
    """Body-fixed rotations (`sequence`, first 3 coordinates) then translations along F's X, Y, Z (last 3)."""
    axes = [_E["XYZ".index(s)] for s in sequence.upper()]
    coordinates = tuple(coordinates)
    return CustomJoint(name, parent, child, coordinates, parent_offset or Transform(), child_offset or Transform(),
                       rotations=_axes(coordinates[:3], axes), translations=_axes(coordinates[3:], _E), kind_name="free")


@dataclass(frozen=True, eq=False)
class SwingJoint(Joint):
    """Two-DOF swing: R_FM = exp([q1 e1 + q2 e2]x), no twist about e3 = e1 x e2.

    ``axes`` holds e1, e2 (orthonormal, in F).  Angular velocity in F is
    J_l(r) (e1 qd1 + e2 qd2) with the SO(3) left Jacobian J_l.
    """

    axes: tuple = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0))
    kind = "swing"

    def __post_init__(self):
        E = np.asarray(self.axes, dtype=float)
        if E.shape != (2, 3) or not np.allclose(E @ E.T, np.eye(2), atol=1e-9):
            raise ValueError("SwingJoint needs two orthonormal axes")
        object.__setattr__(self, "axes", read_only(E))
        if len(self.coordinates) != 2:
            raise ValueError("SwingJoint reads exactly 2 coordinates")

    def motion_subspace(self, qj):
        qj = self._qj(qj)
        N = qj.shape[0]
        E = self.axes.T                            # (3,2)
        r = qj @ E.T
        R = exp_so3(r)
        S = np.zeros((N, 6, 2))
        S[:, :3, :] = left_jacobian_so3(r) @ E
        return R, np.zeros((N, 3)), S


@dataclass(frozen=True, eq=False)
class ExpMapSpherical(Joint):
    """Spherical joint parameterised by a rotation vector: R_FM = exp([q]x), omega_F = J_l(q) qd.

    Free of gimbal lock for |q| < 2 pi (IK keeps |q| <= pi by re-wrapping).
    """

    kind = "expmap"

    def __post_init__(self):
        if len(self.coordinates) != 3:
            raise ValueError("ExpMapSpherical reads exactly 3 coordinates")

    def motion_subspace(self, qj):
        qj = self._qj(qj)
        N = qj.shape[0]
        S = np.zeros((N, 6, 3))
        S[:, :3, :] = left_jacobian_so3(qj)
        return exp_so3(qj), np.zeros((N, 3)), S
