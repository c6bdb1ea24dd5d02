"""Parametric lower-body phantom whose landmarks, axes and joint frames are exact.

Model
-----
Every bone is a smooth union (polynomial smooth-min, blend width ``k``) of
analytic solids (spheres, round cones, ellipsoids, superellipsoids, capped
cylinders, a waisted neck) defined in a per-bone LOCAL frame, right-side
construction.  The standing pose places each bone in the BODY frame
(X anterior, Y superior, Z to the subject's right, origin on the floor,
the right foot's plantar support plane is ``Y = 0``) through a chain of joint
transforms (pelvis -> hip -> femur -> knee -> tibia/fibula/patella -> ankle ->
talus -> subtalar -> calcaneus -> mtp -> toes).  Left bones are the right-side
construction (with the left-side sizes) reflected through the sagittal plane
``Z = 0``.  ``Phantom.placement`` (``scanner_from_body``, rigid, metres) puts
the body in the scanner.

Landmarks are exact by construction: each surface landmark is the extreme point
of a convex part (sphere pole, ellipsoid vertex) lying farther than the blend
width from every other part, so the smooth union leaves it on the surface
(the tests check ``sdf == 0`` there).  Joint surfaces are congruent in the
standing pose: acetabulum centre == femoral head centre, femur and tibia share
the knee axis, tibial plafond and talar dome share the ankle axis.  The talus carries
the subtalar axis of Parr et al. (2012): the line through the centres of its
convex talar head sphere and of its concave posterior-facet sphere.  Bones that
would interpenetrate are carved by their dilated neighbour (cartilage gap).
The constructions themselves are `phantoms.bone_shapes`.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np

from lowerlimb.bones import BONE_NAMES
from lowerlimb.geometry import frame_yz, frame_zy, unit

from .bone_shapes import MIRROR, X, Y, Z, BoneShape, apply_pose, axis_rotation, build_bones, pose_matrix
from .sdf import SDF, rotation_from_axes

__all__ = ["PhantomParams", "Phantom", "make_phantom", "random_placement"]


# --------------------------------------------------------------------------- parameters
@dataclass(frozen=True)
class PhantomParams:
    """Parameters of one synthetic subject.

    Attributes
    ----------
    stature : float
        Standing height, m; every length scales with ``stature / 1.75``.
    femoral_anteversion_deg : float
        Angle of the femoral neck axis anterior to the knee (condylar) axis,
        about the femoral shaft axis, degrees.
    neck_shaft_deg : float
        Angle between femoral neck axis and shaft axis, degrees.
    tibial_torsion_deg : float
        External rotation of the ankle axis relative to the knee axis about the
        tibial long axis, degrees.
    asymmetry : float
        Relative left/right size difference: right sizes x ``(1 + a/2)``, left
        ``(1 - a/2)``.
    variation : float
        Standard deviation of the random log-normal scaling of each body part
        (drawn from the seed, shared by both sides).
    placement : "random" | "identity" | array (4, 4)
        ``scanner_from_body`` rigid transform (metres); ``"random"`` draws a
        supine pose tilted 6-15 degrees about each image axis, from the seed.
    """

    stature: float = 1.75
    femoral_anteversion_deg: float = 13.0
    neck_shaft_deg: float = 128.0
    tibial_torsion_deg: float = 25.0
    asymmetry: float = 0.01
    variation: float = 0.03
    placement: Any = "random"

    def to_json(self) -> dict:
        d = asdict(self)
        d["placement"] = np.asarray(self.placement).tolist() if not isinstance(self.placement, str) else self.placement
        return d


def _check_params(p: PhantomParams) -> None:
    from lowerlimb.errors import InputError

    if not (1.2 <= p.stature <= 2.3):
        raise InputError("stature", f"{p.stature} m is outside 1.2-2.3 m (give metres)")
    if not (100 <= p.neck_shaft_deg <= 160):
        raise InputError("neck_shaft_deg", f"{p.neck_shaft_deg} is outside 100-160 degrees")
    if not (-30 <= p.femoral_anteversion_deg <= 50):
        raise InputError("femoral_anteversion_deg", f"{p.femoral_anteversion_deg} is outside -30..50 degrees")
    if not (-20 <= p.tibial_torsion_deg <= 60):
        raise InputError("tibial_torsion_deg", f"{p.tibial_torsion_deg} is outside -20..60 degrees")
    if not (0 <= abs(p.asymmetry) <= 0.2):
        raise InputError("asymmetry", f"{p.asymmetry} is outside -0.2..0.2")
    if not (0 <= p.variation <= 0.2):
        raise InputError("variation", f"{p.variation} is outside 0..0.2")


def random_placement(rng: np.random.Generator) -> np.ndarray:
    """Supine scanner placement tilted 6-15 degrees about each image axis (random signs).

    Body X (anterior) -> scanner +y, Y (superior) -> +z, Z (right) -> +x
    (RAS-like), then a random rotation so that no bone axis is aligned with
    the image axes, and a translation putting the knees near the scanner origin.
    """
    base = np.column_stack([[0, 1, 0], [0, 0, 1], [1, 0, 0]]).astype(float)
    # tilt about each image axis by 6-15 degrees (random sign) so that no body axis stays aligned
    ang = np.deg2rad(rng.uniform(6.0, 15.0, size=3)) * rng.choice([-1.0, 1.0], size=3)
    R = axis_rotation(Z, ang[2]) @ axis_rotation(Y, ang[1]) @ axis_rotation(X, ang[0]) @ base
    t = -R @ np.array([0.0, 0.5, 0.0]) + rng.normal(scale=0.02, size=3)
    return pose_matrix(t, R)


# --------------------------------------------------------------------------- frames (rules)
# --------------------------------------------------------------------------- phantom
class Phantom:
    """A constructed synthetic subject (immutable).

    Attributes
    ----------
    params : PhantomParams
        Resolved parameters (``placement`` as a 4x4 list-able array).
    placement : ndarray (4, 4)
        ``scanner_from_body`` rigid transform, metres.
    bone_names : tuple of str
        Canonical names of the bones present (see `lowerlimb.bones`).
    body_from_local : dict[str, ndarray (4, 4)]
        Standing-pose transform of each bone's local (construction) frame; left
        bones include the sagittal reflection (determinant -1).
    """

    def __init__(self, params: PhantomParams, seed: int, side: str = "both"):
        _check_params(params)
        rng = np.random.default_rng(seed)
        self.seed = int(seed)
        self.side = side
        bones, self._dims, self._mult = build_bones(params, rng)
        if isinstance(params.placement, str):
            if params.placement == "identity":
                placement = np.eye(4)
            elif params.placement == "random":
                placement = random_placement(np.random.default_rng([int(seed), 7]))
            else:
                from lowerlimb.errors import InputError
                raise InputError("placement", f"unknown placement {params.placement!r} (random, identity or a 4x4 matrix)")
        else:
            placement = np.asarray(params.placement, float)
            R = placement[:3, :3]
            if placement.shape != (4, 4) or not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
                from lowerlimb.errors import InputError
                raise InputError("placement", "must be a 4x4 rigid transform (rotation + translation, metres)")
        self.placement = placement
        self.params = replace(params, placement=placement)
        keep = {"both": ("r", "l"), "r": ("r",), "l": ("l",)}[side]
        self.bone_names = tuple(b for b in BONE_NAMES if b == "pelvis" or b[-1] in keep)
        self._bones = {k: bones[k] for k in self.bone_names}
        self.body_from_local = {k: b.body_from_local for k, b in self._bones.items()}
        self._mesh_cache: dict = {}

    # ---------------------------------------------------------------- geometry
    def scanner_from_local(self, bone: str) -> np.ndarray:
        """4x4 transform from the bone's construction frame to the scanner (may include a reflection)."""
        return self.placement @ self._bone(bone).body_from_local

    def _bone(self, bone: str) -> BoneShape:
        try:
            return self._bones[bone]
        except KeyError:
            from lowerlimb.errors import InputError
            raise InputError(bone, f"not a bone of this phantom ({', '.join(self.bone_names)})") from None

    def local_sdf(self, bone: str) -> SDF:
        """The bone's SDF in its local construction frame (for posing)."""
        return self._bone(bone).sdf

    def sdf(self, bone: str, pts: np.ndarray) -> np.ndarray:
        """Signed distance (m, negative inside) of scanner-frame points ``(N, 3)`` (m) to `bone`."""
        A = self.scanner_from_local(bone)
        p = np.asarray(pts, float).reshape(-1, 3)
        return self._bone(bone).sdf(np.einsum("ij,jk->ik", p - A[:3, 3], A[:3, :3]))

    def local_bounds(self, bone: str) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = self._bone(bone).sdf.bounds()
        return np.asarray(lo, float), np.asarray(hi, float)

    def bounds(self, bone: str, pad: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Scanner-frame axis-aligned box (lo, hi) enclosing `bone`, metres."""
        lo, hi = self.local_bounds(bone)
        A = self.scanner_from_local(bone)
        c, h = (lo + hi) / 2, (hi - lo) / 2
        cc = A[:3, :3] @ c + A[:3, 3]
        hh = np.abs(A[:3, :3]) @ h
        return cc - hh - pad, cc + hh + pad

    def mesh(self, bone: str):
        """Exact reference surface of `bone` (trimesh.Trimesh, scanner frame, metres); cached."""
        from .surface import local_mesh

        if bone not in self._mesh_cache:
            # thin bones (radii of 3-7 mm) get a finer grid: chordal error ~ e^2 / (8 R)
            fine = bone.split("_")[0] in ("toes", "talus", "patella", "fibula")
            self._mesh_cache[bone] = local_mesh(self._bone(bone).sdf, self.local_bounds(bone),
                                                spacing=5e-4 if fine else 8e-4)
        m = self._mesh_cache[bone].copy()
        A = self.scanner_from_local(bone)
        m.apply_transform(A)  # trimesh flips winding itself for reflections
        return m

    def surface_distance(self, bone: str, pts: np.ndarray) -> np.ndarray:
        """Exact signed Euclidean distance (m, negative inside) to the reference mesh of `bone`.

        `sdf` is Euclidean only to first order (smooth unions and normalised
        implicit parts deviate by ~0.1-0.4 mm at 1-3 mm from the surface); use
        this (libigl, slower) to score surface or distance estimates.
        """
        import igl

        m = self.mesh(bone)
        p = np.asarray(pts, float).reshape(-1, 3)
        return np.asarray(igl.signed_distance(p, np.asarray(m.vertices), np.asarray(m.faces, np.int64))[0], float)

    def surface_checks(self) -> dict[str, np.ndarray]:
        """Extra exact surface points used by the tests (scanner frame): name -> (N, 3)."""
        out = {}
        for b in self.bone_names:
            for k, v in self._bones[b].checks.items():
                out[f"{b}.{k}"] = apply_pose(self.placement, v)
        return out

    def posed(self, body_from_local: dict[str, np.ndarray]) -> "Phantom":
        """A copy with some bones moved rigidly (for motion phantoms).

        Parameters
        ----------
        body_from_local : dict[str, ndarray (4, 4)]
            New body-frame transform of each moved bone's local frame; derive it
            from the standing one, e.g. ``ph.body_from_local["tibia_r"] @ T`` or
            ``G @ ph.body_from_local["tibia_r"]`` for a rigid motion ``G`` of
            the body frame.  Landmarks, axes and frames move with their bone;
            joint frames are rebuilt from the parent bone's landmarks.
        """
        import copy

        out = copy.copy(self)
        out._bones = dict(self._bones)
        for bone, new in body_from_local.items():
            old = self._bone(bone)
            new = np.asarray(new, float)
            D = new @ np.linalg.inv(old.body_from_local)
            R = D[:3, :3]
            if new.shape != (4, 4) or not np.allclose(R.T @ R, np.eye(3), atol=1e-9) or np.linalg.det(R) < 0:
                from lowerlimb.errors import InputError
                raise InputError(bone, "the new transform must be a rigid motion of the standing one")
            b = BoneShape(old.sdf, new)
            b.landmarks = {k: apply_pose(D, v) for k, v in old.landmarks.items()}
            b.axes = {k: (apply_pose(D, p), R @ dv) for k, (p, dv) in old.axes.items()}
            b.scalars = dict(old.scalars)
            b.checks = {k: apply_pose(D, v) for k, v in old.checks.items()}
            out._bones[bone] = b
        out.body_from_local = {k: b.body_from_local for k, b in out._bones.items()}
        return out

    # ---------------------------------------------------------------- truth
    def body_truth(self) -> dict:
        """Landmarks, axes, scalars, frames and joints in the BODY frame (metres)."""
        B = self._bones
        out: dict[str, dict] = {}
        for name in self.bone_names:
            b = B[name]
            out[name] = {"landmarks": {k: np.asarray(v, float) for k, v in b.landmarks.items()},
                         "axes": {k: (np.asarray(p, float), unit(dv)) for k, (p, dv) in b.axes.items()},
                         "scalars": dict(b.scalars), "frames": {}}
        lm = out["pelvis"]["landmarks"]
        o = (lm["RASI"] + lm["LASI"]) / 2
        zp = unit(lm["RASI"] - lm["LASI"])
        xp = o - (lm["RPSI"] + lm["LPSI"]) / 2
        out["pelvis"]["frames"]["isb"] = (o, rotation_from_axes(z=zp, x=xp))
        joints = {}
        for side in ("r", "l"):
            if f"femur_{side}" not in out:
                continue
            P = "R" if side == "r" else "L"
            f = out[f"femur_{side}"]
            t = out[f"tibia_{side}"]
            fi = out[f"fibula_{side}"]
            ta = out[f"talus_{side}"]
            ca = out[f"calcn_{side}"]
            to = out[f"toes_{side}"]
            pa = out[f"patella_{side}"]
            hc = f["landmarks"]["femoral_head_centre"]
            epi_mid = (f["landmarks"][f"{P}KNE"] + f["landmarks"][f"{P}MFC"]) / 2
            right_epi = f["landmarks"][f"{P}KNE"] - f["landmarks"][f"{P}MFC"]
            if side == "l":
                right_epi = -right_epi
            f["frames"]["isb"] = (hc, frame_yz(hc - epi_mid, right_epi))
            # tibia ISB-like: origin mid-malleoli, Y to the knee centre, Z towards the right malleolus
            mal = (t["landmarks"][f"{P}MMA"] + fi["landmarks"][f"{P}ANK"]) / 2
            kc = f["landmarks"]["intercondylar_midpoint"]
            kc_t = t["axes"]["knee_axis"][0]            # the same point, carried by the tibia
            right_mal = fi["landmarks"][f"{P}ANK"] - t["landmarks"][f"{P}MMA"]
            if side == "l":
                right_mal = -right_mal
            t["frames"]["isb"] = (mal, frame_yz(kc_t - mal, right_mal))
            Rb = self._bones[f"patella_{side}"].body_from_local[:3, :3]
            Rp = MIRROR[:3, :3] @ Rb @ MIRROR[:3, :3] if side == "l" else Rb
            pa["frames"]["articular"] = (pa["landmarks"]["patella_centre"], Rp)
            hcon = ca["landmarks"]["heel_contact"]
            mcon = (ca["landmarks"]["met1_contact"] + ca["landmarks"]["met5_contact"]) / 2
            n = np.cross(ca["landmarks"]["met1_contact"] - hcon, ca["landmarks"]["met5_contact"] - hcon)
            n = unit(n if n[1] > 0 else -n)
            ca["frames"]["foot"] = (hcon, frame_zy(np.cross(mcon - hcon, n), n))
            # joints
            joints[f"hip_{side}"] = (hc, out["pelvis"]["frames"]["isb"][1])
            kax = f["axes"]["knee_axis"][1]
            joints[f"knee_{side}"] = (kc, frame_zy(kax, hc - kc))
            ac = ta["landmarks"]["talar_dome_centre"]
            joints[f"ankle_{side}"] = (ac, frame_zy(ta["axes"]["ankle_axis"][1], kc_t - t["axes"]["ankle_axis"][0]))
            sp, sd = ta["axes"]["subtalar_axis"]
            talus_up = self._bones[f"talus_{side}"].body_from_local[:3, 1]   # talus (ankle-frame) superior axis
            joints[f"subtalar_{side}"] = (sp, frame_zy(sd, talus_up))      # the posterior facet centre
            mp, md = to["axes"]["mtp_axis"]
            joints[f"mtp_{side}"] = (mp, frame_zy(md, n))
        return {"bones": out, "joints": joints}

    def truth(self) -> dict:
        """Ground truth in the scanner frame (metres), the schema of ``truth.json``."""
        A = self.placement
        R = A[:3, :3]
        P = lambda p: (R @ np.asarray(p) + A[:3, 3]).tolist()  # noqa: E731
        bt = self.body_truth()
        zeros = np.zeros((3, 3)).tolist()
        bones = {}
        for name, b in bt["bones"].items():
            bones[name] = {
                "landmarks": {k: {"position": P(v), "cov": zeros} for k, v in b["landmarks"].items()},
                "axes": {k: {"point": P(p), "direction": (R @ dv).tolist(), "sd_deg": 0.0} for k, (p, dv) in b["axes"].items()},
                "scalars": {k: {"value": float(v), "sd": 0.0} for k, v in b["scalars"].items()},
                "frames": {k: {"origin": P(o), "rotation": (R @ Rf).tolist()} for k, (o, Rf) in b["frames"].items()},
            }
        joints = {k: {"origin": P(o), "origin_cov": zeros, "rotation": (R @ Rf).tolist(), "axis_sd_deg": 0.0}
                  for k, (o, Rf) in bt["joints"].items()}
        return {"units": "m", "frame": "scanner", "params": self.params.to_json() | {"seed": self.seed, "side": self.side},
                "landmarks": {"units": "m", "frame": "input", "bones": bones},
                "joints": {"units": "m", "frame": "input", "joints": joints}}


def make_phantom(seed: int = 0, side: str = "both", **overrides) -> Phantom:
    """Build a phantom: ``PhantomParams(**overrides)`` with random variation from `seed`.

    Parameters
    ----------
    seed : int
        Seeds the per-part size variation and the random scanner placement.
    side : {"both", "r", "l"}
        Which legs to include (the pelvis is always present).
    **overrides
        Fields of `PhantomParams`.
    """
    from lowerlimb.errors import InputError

    if side not in ("both", "r", "l"):
        raise InputError("side", f"{side!r} is not one of both, r, l")
    fields = set(PhantomParams.__dataclass_fields__)
    bad = set(overrides) - fields
    if bad:
        raise InputError(", ".join(sorted(bad)), f"unknown phantom parameter (known: {', '.join(sorted(fields))})")
    return Phantom(PhantomParams(**overrides), seed=seed, side=side)
