"""Immutable multibody model description (pinocchio-style Model, state kept apart).

A `Model` holds bodies (mass properties), one joint per non-ground body
(a kinematic tree rooted at ``ground``), the generalized coordinates with
their limits, extra frames and markers fixed to bodies, and the linear
coordinate couplings / inequalities and non-linear coordinate couplers.  It
never changes after construction; every evaluation (FK, Jacobians, IK) takes
the model and a coordinate array ``q`` of shape (n_q,) or (N, n_q).

Bodies are stored in topological order: ``bodies[0]`` is the ground and
``joints[i]`` is the joint whose child is ``bodies[i + 1]``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from kinematics.multibody.coupling import CoordinateCoupler, LinearCoupling, LinearInequalities
from kinematics.multibody.functions import read_only
from kinematics.multibody.joints import Joint, Transform

__all__ = ["Body", "Coordinate", "Marker", "Frame", "Model", "GROUND"]

GROUND = "ground"


@dataclass(frozen=True, eq=False)
class Body:
    """Rigid body: mass (kg), centre of mass `com` (m, body frame), `inertia` (kg m^2, 3x3 about the com, body axes)."""

    name: str
    mass: float = 0.0
    com: np.ndarray = field(default_factory=lambda: np.zeros(3))
    inertia: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))

    def __post_init__(self):
        com = read_only(self.com)
        I = np.asarray(self.inertia, dtype=float)
        if I.shape == (6,):  # OpenSim [Ixx Iyy Izz Ixy Ixz Iyz]
            xx, yy, zz, xy, xz, yz = I
            I = np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])
        if com.shape != (3,) or I.shape != (3, 3):
            raise ValueError(f"body {self.name!r}: com must be a 3-vector and inertia 3x3 (or OpenSim's 6 values)")
        if self.mass < 0:
            raise ValueError(f"body {self.name!r}: negative mass")
        object.__setattr__(self, "com", com)
        object.__setattr__(self, "inertia", read_only(I))


@dataclass(frozen=True)
class Coordinate:
    """Generalized coordinate: ``kind`` is 'rotational' (rad) or 'translational' (m); ``range`` = (lower, upper)."""

    name: str
    kind: str = "rotational"
    default: float = 0.0
    range: tuple[float, float] = (-np.inf, np.inf)
    locked: bool = False
    clamped: bool = False

    def __post_init__(self):
        if self.kind not in ("rotational", "translational", "coupled"):
            raise ValueError(f"coordinate {self.name!r}: kind must be 'rotational' or 'translational'")
        lo, hi = float(self.range[0]), float(self.range[1])
        if lo > hi:
            raise ValueError(f"coordinate {self.name!r}: range lower bound {lo} above upper bound {hi}")
        object.__setattr__(self, "range", (lo, hi))
        object.__setattr__(self, "default", float(self.default))


@dataclass(frozen=True, eq=False)
class Marker:
    """Marker fixed to `body` at `offset` (m, body frame)."""

    name: str
    body: str
    offset: np.ndarray

    def __post_init__(self):
        off = read_only(self.offset)
        if off.shape != (3,):
            raise ValueError(f"marker {self.name!r}: offset must be a 3-vector")
        object.__setattr__(self, "offset", off)


@dataclass(frozen=True, eq=False)
class Frame:
    """Named frame fixed to `body` with pose `offset` (a Transform in the body frame)."""

    name: str
    body: str
    offset: Transform = field(default_factory=Transform)


@dataclass(frozen=True, eq=False)
class Model:
    """Immutable kinematic tree.

    Parameters
    ----------
    bodies : sequence of Body (the ground is added when absent)
    joints : sequence of Joint, one per non-ground body (any order; sorted topologically)
    coordinates : sequence of Coordinate, every coordinate any joint reads
    markers, frames : sequences of Marker / Frame
    couplings : LinearCoupling, optional
        Linear equality rows C q = d enforced exactly by IK.
    inequalities : LinearInequalities, optional
        Rows G q <= h (coordinate limits are handled separately through `Coordinate.range`).
    couplers : sequence of CoordinateCoupler
        Non-linear dependent coordinates q_dep = f(q_indep) (OpenSim CoordinateCouplerConstraint).
    gravity : (3,) m/s^2 in ground
    name : str

    Notes
    -----
    Derived, read-only index tables: ``parent`` (B,) parent body index
    (-1 for the ground); ``joint_coordinate_index[j]`` the model coordinates
    read by joint j (its ``qj`` columns); ``column_coordinate`` (K,) and
    ``column_joint`` (K,) the coordinate and joint of each joint-coordinate
    column k (columns of all joints concatenated in joint order);
    ``body_columns`` (B, K) True where column k moves body b.  Models compare
    and hash by identity, so they can key caches.
    """

    bodies: tuple[Body, ...]
    joints: tuple[Joint, ...]
    coordinates: tuple[Coordinate, ...]
    markers: tuple[Marker, ...] = ()
    frames: tuple[Frame, ...] = ()
    couplings: LinearCoupling | None = None
    inequalities: LinearInequalities | None = None
    couplers: tuple[CoordinateCoupler, ...] = ()
    gravity: np.ndarray = field(default_factory=lambda: np.array([0.0, -9.80665, 0.0]))
    name: str = "model"

    # Derived index tables (filled in __post_init__, read-only).
    parent: np.ndarray = field(init=False, repr=False, compare=False)
    joint_coordinate_index: tuple = field(init=False, repr=False, compare=False)
    column_coordinate: np.ndarray = field(init=False, repr=False, compare=False)
    column_joint: np.ndarray = field(init=False, repr=False, compare=False)
    body_columns: np.ndarray = field(init=False, repr=False, compare=False)
    _index: dict = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        bodies = list(self.bodies)
        if not bodies or bodies[0].name != GROUND:
            bodies = [b for b in bodies if b.name != GROUND]
            bodies.insert(0, Body(GROUND))
        names = [b.name for b in bodies]
        if len(set(names)) != len(names):
            raise ValueError(f"duplicate body names in model {self.name!r}")
        by_child = {}
        for j in self.joints:
            if j.child in by_child:
                raise ValueError(f"body {j.child!r} is the child of two joints (closed loops go in couplings/constraints)")
            if j.child not in names or j.parent not in names:
                raise ValueError(f"joint {j.name!r} connects unknown bodies {j.parent!r} -> {j.child!r}")
            by_child[j.child] = j
        # Topological order (breadth-first from the ground, keeping the given order among siblings).
        order, joints = [GROUND], []
        pending = [b for b in names[1:]]
        while pending:
            progressed = False
            for b in list(pending):
                j = by_child.get(b)
                if j is None:
                    raise ValueError(f"body {b!r} has no joint connecting it to the tree")
                if j.parent in order:
                    order.append(b)
                    joints.append(j)
                    pending.remove(b)
                    progressed = True
            if not progressed:
                raise ValueError(f"bodies {pending} are not connected to the ground (loop in the joint graph)")
        body_by_name = {b.name: b for b in bodies}
        object.__setattr__(self, "bodies", tuple(body_by_name[b] for b in order))
        object.__setattr__(self, "joints", tuple(joints))
        object.__setattr__(self, "coordinates", tuple(self.coordinates))
        object.__setattr__(self, "markers", tuple(self.markers))
        object.__setattr__(self, "frames", tuple(self.frames))
        object.__setattr__(self, "couplers", tuple(self.couplers))
        object.__setattr__(self, "gravity", read_only(self.gravity))
        cnames = [c.name for c in self.coordinates]
        if len(set(cnames)) != len(cnames):
            raise ValueError("duplicate coordinate names")
        bidx = {b: i for i, b in enumerate(order)}
        cidx = {c: i for i, c in enumerate(cnames)}
        parent = np.array([-1] + [bidx[j.parent] for j in joints], dtype=int)
        jci, col_c, col_j = [], [], []
        for ji, j in enumerate(joints):
            missing = [c for c in j.coordinates if c not in cidx]
            if missing:
                raise ValueError(f"joint {j.name!r} reads undeclared coordinates {missing}")
            ix = np.array([cidx[c] for c in j.coordinates], dtype=int)
            ix.setflags(write=False)
            jci.append(ix)
            col_c.extend(ix.tolist())
            col_j.extend([ji] * len(ix))
        K = len(col_c)
        # body_columns[b, k]: column k (a joint coordinate) moves body b (its joint is an ancestor of b).
        bc = np.zeros((len(order), K), dtype=bool)
        col_j_arr = np.array(col_j, dtype=int)
        for b in range(1, len(order)):
            chain, a = set(), b
            while a > 0:
                chain.add(a - 1)
                a = parent[a]
            bc[b] = np.isin(col_j_arr, list(chain))
        for m in self.markers:
            if m.body not in bidx:
                raise ValueError(f"marker {m.name!r} is on unknown body {m.body!r}")
        for f in self.frames:
            if f.body not in bidx:
                raise ValueError(f"frame {f.name!r} is on unknown body {f.body!r}")
        mnames = [m.name for m in self.markers]
        if len(set(mnames)) != len(mnames):
            raise ValueError("duplicate marker names")
        if self.couplings is not None and self.couplings.coordinates != tuple(cnames):
            raise ValueError("couplings must be expressed over the model's coordinates (use LinearCoupling.over)")
        if self.inequalities is not None and self.inequalities.coordinates != tuple(cnames):
            raise ValueError("inequalities must be expressed over the model's coordinates")
        for cp in self.couplers:
            for c in (cp.dependent,) + tuple(cp.independent):
                if c not in cidx:
                    raise ValueError(f"coupler on unknown coordinate {c!r}")
        for arr in (parent, col_c_arr := np.array(col_c, dtype=int), col_j_arr, bc):
            arr.setflags(write=False)
        object.__setattr__(self, "parent", parent)
        object.__setattr__(self, "joint_coordinate_index", tuple(jci))
        object.__setattr__(self, "column_coordinate", col_c_arr)
        object.__setattr__(self, "column_joint", col_j_arr)
        object.__setattr__(self, "body_columns", bc)
        object.__setattr__(self, "_index", {
            "body": bidx, "coordinate": cidx, "marker": {m: i for i, m in enumerate(mnames)},
            "frame": {f.name: i for i, f in enumerate(self.frames)}, "joint": {j.name: i for i, j in enumerate(joints)},
        })

    # ------------------------------------------------------------------ sizes and look-ups
    @property
    def n_q(self) -> int:
        return len(self.coordinates)

    @property
    def n_bodies(self) -> int:
        return len(self.bodies)

    @property
    def coordinate_names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.coordinates)

    @property
    def marker_names(self) -> tuple[str, ...]:
        return tuple(m.name for m in self.markers)

    @property
    def body_names(self) -> tuple[str, ...]:
        return tuple(b.name for b in self.bodies)

    def _lookup(self, kind: str, name: str) -> int:
        try:
            return self._index[kind][name]
        except KeyError:
            raise KeyError(f"model {self.name!r} has no {kind} {name!r}") from None

    def body_index(self, name: str) -> int:
        return self._lookup("body", name)

    def coordinate_index(self, name: str) -> int:
        return self._lookup("coordinate", name)

    def marker_index(self, name: str) -> int:
        return self._lookup("marker", name)

    def joint(self, name: str) -> Joint:
        return self.joints[self._index["joint"][name]]

    def frame(self, name: str) -> Frame:
        return self.frames[self._index["frame"][name]]

    def marker(self, name: str) -> Marker:
        return self.markers[self.marker_index(name)]

    @property
    def default_q(self) -> np.ndarray:
        return np.array([c.default for c in self.coordinates])

    @property
    def lower(self) -> np.ndarray:
        return np.array([c.range[0] for c in self.coordinates])

    @property
    def upper(self) -> np.ndarray:
        return np.array([c.range[1] for c in self.coordinates])

    @property
    def rotational(self) -> np.ndarray:
        """Boolean mask of rotational coordinates."""
        return np.array([c.kind == "rotational" for c in self.coordinates])

    @property
    def total_mass(self) -> float:
        return float(sum(b.mass for b in self.bodies))

    def replace(self, **changes) -> "Model":
        """A new model with some constructor fields replaced (e.g. markers, couplings)."""
        kw = dict(bodies=self.bodies, joints=self.joints, coordinates=self.coordinates, markers=self.markers,
                  frames=self.frames, couplings=self.couplings, inequalities=self.inequalities,
                  couplers=self.couplers, gravity=self.gravity, name=self.name)
        kw.update(changes)
        return Model(**kw)

    def with_couplings(self, couplings: LinearCoupling | None) -> "Model":
        return self.replace(couplings=couplings)

    def random_q(self, n: int, rng: np.random.Generator, span: float = np.pi / 2) -> np.ndarray:
        """Uniform random coordinates within the limits (infinite ranges -> default +- span), shape (n, n_q)."""
        lo, hi = self.lower.copy(), self.upper.copy()
        d = self.default_q
        lo = np.where(np.isfinite(lo), lo, d - np.where(self.rotational, span, 0.5))
        hi = np.where(np.isfinite(hi), hi, d + np.where(self.rotational, span, 0.5))
        return lo + (hi - lo) * rng.random((n, self.n_q))
