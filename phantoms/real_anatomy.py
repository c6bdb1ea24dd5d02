"""Phantoms built on real anatomy: a subject's bone meshes and an expert-built model of the same bones.

The expert model (an ``.osim`` whose bodies are in the imaging frame, as the
STAPLE data sets' ``manual_*.osim``: each joint's frame is the joint centre and
axes in scanner coordinates) IS the truth skeleton: its joint frames, its
transform axes, its coordinates; its bodies carry the meshes.

Frames
------
* scanner: the meshes' frame (metres here; the PLY files are mm).  The right
  bodies' local frames are the scanner frame (as in the expert model), so the
  expert's joint offsets are used unchanged.
* mirroring: a one-sided subject is completed by the pelvis's own symmetry
  ``S(x) = M x + c`` (``det M = -1``): the reflection about the expert pelvis
  frame's sagittal plane, refined by rigid ICP of the mirrored pelvis onto
  itself (`pelvis_symmetry`).  A mirrored body's local coordinates are
  ``l = D r`` (``D = diag(1, 1, -1)``, ``r`` the twin's local coordinates), its
  placement at the scan pose the proper rigid map ``x = M D l + c``.  Mirrored
  joint frames are then ``(D o, D R D)`` in mirrored bodies, ``(M o + c, M R D)``
  in the pelvis, and every rotation axis ``a`` becomes ``-D a`` (translations
  ``D a``): the same coordinate values give the mirror-image motion, so the
  left coordinates keep gait2392's meaning and signs.
* model ground: OpenSim's convention (X forward, Y up, Z right) carried into
  the lab by the constant ``lab_from_model`` rotation and offset of
  `phantoms.lab.Lab` (the ground_pelvis joint's parent frame), so the truth
  ``.osim`` has ground = lab and OpenSim's IK runs on the trials as written.

Label volumes (`mesh_label_volume`)
-----------------------------------
A voxel belongs to a bone when at least half of it is inside the mesh (the
analytic phantoms' rule, `phantoms.imaging`), the inside fraction measured
along 16 rays per voxel column from the rays' exact crossings with the mesh
(Open3D ``list_intersections``; trimesh's point-wise ``contains`` or a signed
distance per voxel is 10-100x slower).
"""
from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from lowerlimb.errors import InputError
from lowerlimb.geometry import kabsch

__all__ = ["RealAnatomy", "load_real_anatomy", "pelvis_symmetry", "mesh_label_volume", "D_MIRROR", "SEGMENT_BONES"]

D_MIRROR = np.diag([1.0, 1.0, -1.0])
#: bones carried by each body base name (fibula and patella ride on the tibia, as in the STAPLE expert
#: models; the toes on the calcaneus when the model has no toes body)
SEGMENT_BONES = {"pelvis": ("pelvis",), "femur": ("femur",), "tibia": ("tibia", "fibula", "patella"),
                 "talus": ("talus",), "calcn": ("calcn", "toes"), "toes": ("toes",)}
_BONE_FILES = {"pelvis": ("pelvis_no_sacrum", "pelvis"), "femur": ("femur",), "patella": ("patella",),
               "tibia": ("tibia_no_fib", "tibia"), "fibula": ("fibula",), "talus": ("talus",), "calcn": ("calcn",),
               "toes": ("toes",)}


def _side_of(name: str) -> str | None:
    m = re.search(r"_([rl])$", name)
    return m.group(1) if m else None


def _twin(name: str) -> str:
    s = _side_of(name)
    return name if s is None else name[:-1] + ("l" if s == "r" else "r")


@dataclass(frozen=True)
class RealAnatomy:
    """A real subject's bones and its expert-built two-sided truth skeleton.

    Attributes
    ----------
    name : str (the anatomy folder's name)
    meshes : dict bone -> trimesh.Trimesh, scanner frame, metres (the mirrored side included)
    local_meshes : dict bone -> trimesh.Trimesh in its body's local frame (metres)
    bone_body : dict bone -> body name
    model : kinematics.multibody.model.Model, the truth skeleton (no markers, model ground: X forward, Y up, Z right)
    mirrored : tuple of bone names made by mirroring; symmetry : (M (3, 3), c (3,)) or None
    scan_q : (n_q,) joint coordinates of the scan pose (pelvis coordinates 0)
    joints_scanner : dict joint -> (origin (3,), rotation (3, 3)) parent-side joint frames at the scan pose
    fibula_from : "mesh" (fibula_r.ply) or "tibia component" (second component of the tibia mesh)
    sources : dict of the files read
    """

    name: str
    meshes: dict
    local_meshes: dict
    bone_body: dict
    model: object
    mirrored: tuple
    symmetry: tuple | None
    scan_q: np.ndarray
    joints_scanner: dict
    fibula_from: str
    sources: dict
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def bone_names(self) -> tuple[str, ...]:
        return tuple(self.meshes)

    @property
    def sides(self) -> tuple[str, ...]:
        return tuple(s for s in ("r", "l") if f"femur_{s}" in self.model.body_names)

    def bounds(self, bone: str, pad: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = self.meshes[bone].bounds
        return lo - pad, hi + pad

    def mesh(self, bone: str):
        return self.meshes[bone]

    def body_vertices(self, body: str) -> np.ndarray:
        """Vertices (N, 3) of every bone carried by `body`, in its local frame."""
        key = ("verts", body)
        if key not in self._cache:
            v = [np.asarray(self.local_meshes[b].vertices) for b, bb in self.bone_body.items() if bb == body]
            self._cache[key] = np.concatenate(v) if v else np.zeros((0, 3))
        return self._cache[key]


def _load_ply_m(path: Path):
    import trimesh

    try:
        m = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:
        raise InputError(path, f"not a readable mesh ({type(exc).__name__}: {exc})") from None
    if len(m.faces) == 0:
        raise InputError(path, "mesh has no faces")
    m = trimesh.Trimesh(np.asarray(m.vertices, float) * 1e-3, np.asarray(m.faces), process=False)
    ext = np.ptp(m.vertices, axis=0).max()
    if not (0.005 < ext < 1.0):
        raise InputError(path, f"mesh extent {ext * 1e3:.0f} mm is not a bone in millimetres")
    return m


def _find_bone_files(folder: Path) -> dict:
    files = {p.stem.lower(): p for p in folder.iterdir() if p.suffix.lower() in (".ply", ".stl", ".obj")}
    found = {}
    for s in ("r", "l"):
        for base, cands in _BONE_FILES.items():
            for c in cands:
                key = c if base == "pelvis" else f"{c}_{s}"
                if key in files:
                    found[base if base == "pelvis" else f"{base}_{s}"] = files[key]
                    break
    full_tibia = {s: files.get(f"tibia_{s}") for s in ("r", "l")}
    return found, full_tibia


def _split_tibia(mesh):
    """(tibia, fibula or None): the largest component and, when there is one, the second largest."""
    import trimesh

    parts = sorted(mesh.split(only_watertight=False), key=lambda m: -abs(m.area))
    parts = [p for p in parts if len(p.faces) > 200]
    if len(parts) < 2:
        return mesh, None
    return parts[0], trimesh.Trimesh(parts[1].vertices, parts[1].faces, process=False)


def pelvis_symmetry(vertices: np.ndarray, origin: np.ndarray, normal: np.ndarray, iterations: int = 40,
                    n_points: int = 4000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The pelvis's symmetry ``S(x) = M x + c`` (det M = -1): a reflection refined by rigid ICP.

    Start: reflection about the plane through `origin` with unit `normal`.  Then
    point-to-point ICP (Besl & McKay 1992) of the mirrored vertices onto the
    originals: ``S <- T S`` with T the rigid Kabsch fit of ``S(x_i)`` to their
    nearest pelvis vertices (pairs beyond 3 median distances dropped).

    Returns
    -------
    M : (3, 3) improper orthogonal; c : (3,) m
    """
    from scipy.spatial import cKDTree

    n = np.asarray(normal, float) / np.linalg.norm(normal)
    M = np.eye(3) - 2.0 * np.outer(n, n)
    c = 2.0 * np.dot(origin, n) * n
    V = np.asarray(vertices, float)
    rng = np.random.default_rng(seed)
    P = V[rng.choice(len(V), size=min(n_points, len(V)), replace=False)]
    tree = cKDTree(V)
    for _ in range(iterations):
        X = P @ M.T + c
        d, i = tree.query(X)
        keep = d < 3.0 * np.median(d) + 1e-9
        A, B = X[keep], V[i[keep]]
        R, t = kabsch(A, B)
        M, c = R @ M, R @ c + t
        if np.linalg.norm(t) < 1e-7 and np.abs(R - np.eye(3)).max() < 1e-8:
            break
    U, _, Wt = np.linalg.svd(M)             # exact orthogonality
    return U @ Wt, c


def _mirror_transform(T, in_pelvis: bool, M, c):
    from kinematics.multibody.joints import Transform

    if in_pelvis:
        return Transform(M @ T.rotation @ D_MIRROR, M @ T.translation + c)
    return Transform(D_MIRROR @ T.rotation @ D_MIRROR, D_MIRROR @ T.translation)


def _rename(name: str, side_from: str, side_to: str) -> str:
    return re.sub(rf"_{side_from}$", f"_{side_to}", name)


def _scan_coordinates(model, bodies_identity) -> np.ndarray:
    """Coordinates putting every body of `bodies_identity` at the identity pose relative to the pelvis."""
    from scipy.optimize import least_squares

    from kinematics.algorithms.fk import forward_kinematics

    q = np.zeros(model.n_q)
    pel = model.body_index("pelvis")
    free = [i for i, c in enumerate(model.coordinate_names) if not c.startswith("pelvis_")]

    def res(x):
        qq = q.copy()
        qq[free] = x
        st = forward_kinematics(model, qq)
        Rp, pp = st.rotations[0, pel], st.positions[0, pel]
        r = []
        for b in bodies_identity:
            k = model.body_index(b)
            R = Rp.T @ st.rotations[0, k]
            p = Rp.T @ (st.positions[0, k] - pp)
            r.append((R - np.eye(3)).ravel())
            r.append(p * 10.0)
        return np.concatenate(r)

    sol = least_squares(res, np.zeros(len(free)), xtol=1e-14, ftol=1e-14, gtol=1e-14)
    q[free] = sol.x
    return q


def load_real_anatomy(anatomy_dir: str | os.PathLike, reference: str | os.PathLike, *,
                      progress: Callable[[str], None] | None = None) -> RealAnatomy:
    """Read a subject's bone meshes (mm) and its expert model; complete the missing side by mirroring.

    Parameters
    ----------
    anatomy_dir : folder of PLY/STL meshes named as the STAPLE data sets (``pelvis_no_sacrum`` or
        ``pelvis``, ``femur_r``, ``tibia_r`` (with or without the fibula as a second component),
        ``fibula_r``, ``patella_r``, ``talus_r``, ``calcn_r``, ``toes_r``)
    reference : expert ``.osim`` of the same bones, bodies in the scanner frame (OpenSim 3 or 4)

    Raises
    ------
    InputError : a missing folder/file, a mesh that is not a bone in mm, a model without pelvis or
        hip, a model whose joints lie off the meshes.
    """
    import trimesh

    from kinematics.multibody.joints import CustomJoint, TransformAxis
    from kinematics.multibody.model import Body, Coordinate, Model
    from kinematics.io.opensim_io import load_osim

    say = progress or (lambda m: None)
    folder = Path(anatomy_dir)
    if not folder.is_dir():
        raise InputError(folder, "anatomy folder not found")
    ref = load_osim(reference)
    found, full_tibia = _find_bone_files(folder)
    if "pelvis" not in found:
        raise InputError(folder, "no pelvis mesh (pelvis_no_sacrum.ply or pelvis.ply)")
    if "pelvis" not in ref.body_names:
        raise InputError(reference, "the reference model has no pelvis body")
    model_sides = [s for s in ("r", "l") if f"femur_{s}" in ref.body_names]
    if not model_sides:
        raise InputError(reference, "the reference model has no femur_r or femur_l body")
    say("reading meshes")
    meshes = {}
    for bone, p in found.items():
        meshes[bone] = _load_ply_m(p)
    fibula_from = "mesh"
    for s in model_sides:
        if f"tibia_{s}" not in meshes:
            raise InputError(folder, f"no tibia_{s} mesh")
        tib, fib = _split_tibia(meshes[f"tibia_{s}"])
        if fib is None and full_tibia.get(s) is not None and full_tibia[s] != found.get(f"tibia_{s}"):
            _, fib = _split_tibia(_load_ply_m(full_tibia[s]))
        meshes[f"tibia_{s}"] = tib
        if f"fibula_{s}" not in meshes:
            if fib is None:
                raise InputError(folder, f"no fibula_{s} mesh and no fibula component in the tibia_{s} mesh")
            meshes[f"fibula_{s}"] = fib
            fibula_from = "tibia component"
    ref_bodies = set(ref.body_names)
    bone_body = {}
    for bone in list(meshes):
        s = _side_of(bone)
        base = bone if s is None else bone[:-2]
        if s is not None and s not in model_sides:
            meshes.pop(bone)
            continue
        body = next((b if b == "pelvis" else f"{b}_{s}" for b, bones in SEGMENT_BONES.items()
                     if base in bones and (b if b == "pelvis" else f"{b}_{s}") in ref_bodies
                     and not (base == "toes" and b == "calcn" and f"toes_{s}" in ref_bodies)), None)
        if body is None:
            meshes.pop(bone)
            continue
        bone_body[bone] = body
    # reference joints: check they lie on the meshes (a model of other bones is refused)
    for j in ref.joints:
        if j.parent == "ground":
            continue
        o = j.parent_offset.translation
        near = [b for b, bb in bone_body.items() if bb in (j.parent, j.child)]
        if near:
            d = min(float(np.min(np.linalg.norm(np.asarray(meshes[b].vertices) - o, axis=1))) for b in near)
            if d > 0.05:
                raise InputError(reference, f"joint {j.name} lies {d * 1e3:.0f} mm from its bones' meshes "
                                            "(a model of other bones, or not in the scanner frame?)")
    # ---- pelvis frame and symmetry
    gp = next(j for j in ref.joints if j.child == "pelvis")
    pel_frame = gp.child_offset                         # expert pelvis frame in the pelvis body (= scanner)
    missing = [s for s in ("r", "l") if s not in model_sides]
    M = c = None
    mirrored = ()
    if missing:
        say("mirroring")
        M, c = pelvis_symmetry(np.asarray(meshes["pelvis"].vertices), pel_frame.translation,
                               pel_frame.rotation[:, 2])
    # ---- bodies, joints, coordinates
    bodies = [b for b in ref.bodies if b.name != "ground"]
    joints = []
    coords = {c_.name: c_ for c_ in ref.coordinates}
    coord_list = []
    for j in ref.joints:
        if j is gp:
            continue
        joints.append(j)
    for j in joints:
        for n in j.coordinates:
            coord_list.append(coords[n])
    if missing:
        src = model_sides[0]
        dst = missing[0]
        for b in list(bodies):
            if _side_of(b.name) == src:
                bodies.append(Body(_rename(b.name, src, dst), b.mass, D_MIRROR @ b.com, D_MIRROR @ b.inertia @ D_MIRROR))
        new_joints = []
        for j in joints:
            if _side_of(j.child) != src:
                continue
            ren = {n: _rename(n, src, dst) for n in j.coordinates}
            rot = tuple(TransformAxis(-D_MIRROR @ a.axis, a.function, tuple(ren[n] for n in a.coordinates))
                        for a in j.rotations)
            tr = tuple(TransformAxis(D_MIRROR @ a.axis, a.function, tuple(ren[n] for n in a.coordinates))
                       for a in j.translations)
            new_joints.append(CustomJoint(
                _rename(j.name, src, dst), _rename(j.parent, src, dst), _rename(j.child, src, dst),
                tuple(ren[n] for n in j.coordinates),
                _mirror_transform(j.parent_offset, j.parent == "pelvis", M, c),
                _mirror_transform(j.child_offset, False, M, c),
                rotations=rot, translations=tr, kind_name="custom"))
            for n in j.coordinates:
                c0 = coords[n]
                coord_list.append(Coordinate(ren[n], c0.kind, c0.default, c0.range, c0.locked, c0.clamped))
        joints += new_joints
        for bone in [b for b in meshes if _side_of(b) == src]:
            m = meshes[bone]
            v = np.asarray(m.vertices) @ M.T + c
            twin = _twin(bone)
            meshes[twin] = trimesh.Trimesh(v, np.asarray(m.faces)[:, ::-1], process=False)
            bone_body[twin] = _rename(bone_body[bone], src, dst)
        mirrored = tuple(b for b in meshes if _side_of(b) == dst)
    # ground-pelvis: gait2392's free joint (tilt Z, list X, rotation Y, then translations), child frame = expert's
    pelvis_coords = [Coordinate("pelvis_tilt"), Coordinate("pelvis_list"), Coordinate("pelvis_rotation"),
                     Coordinate("pelvis_tx", "translational"), Coordinate("pelvis_ty", "translational"),
                     Coordinate("pelvis_tz", "translational")]
    E = np.eye(3)
    ax = lambda v, n: TransformAxis(v, _linear(), (n,))  # noqa: E731
    ground = CustomJoint("ground_pelvis", "ground", "pelvis", tuple(c_.name for c_ in pelvis_coords),
                         child_offset=pel_frame,
                         rotations=(ax(E[2], "pelvis_tilt"), ax(E[0], "pelvis_list"), ax(E[1], "pelvis_rotation")),
                         translations=(ax(E[0], "pelvis_tx"), ax(E[1], "pelvis_ty"), ax(E[2], "pelvis_tz")),
                         kind_name="custom")
    order = {b.name: i for i, b in enumerate(bodies)}
    joints = sorted(joints, key=lambda j: order.get(j.child, 99))
    model = Model(tuple([b for b in bodies]), tuple([ground] + joints), tuple(pelvis_coords + coord_list),
                  name=f"truth_{folder.name}")
    # local meshes: right (reference side) bodies are the scanner frame; mirrored ones l = D r
    local = {}
    for bone, m in meshes.items():
        if bone in mirrored:
            tw = meshes[_twin(bone)]
            local[bone] = trimesh.Trimesh(np.asarray(tw.vertices) @ D_MIRROR, np.asarray(tw.faces)[:, ::-1], process=False)
        else:
            local[bone] = m
    body_names = [b for b in model.body_names if b not in ("ground", "pelvis") and _side_of(b) not in missing]
    scan_q = _scan_coordinates(model, body_names)
    for i, n in enumerate(model.coordinate_names):     # the mirrored side's scan pose is the mirror image
        if missing and _side_of(n) == missing[0]:
            scan_q[i] = scan_q[model.coordinate_index(_rename(n, missing[0], model_sides[0]))]
    js = {}
    for j in model.joints:
        if j.parent == "ground":
            continue
        T = j.parent_offset
        if j.parent != "pelvis" and _side_of(j.parent) in missing:
            R, o = M @ D_MIRROR @ T.rotation, M @ D_MIRROR @ T.translation + c
        else:
            R, o = T.rotation, T.translation
        js[j.name] = (np.asarray(o, float), np.asarray(R, float))
    sources = {"anatomy": os.fspath(folder), "reference": os.fspath(reference),
               "meshes": {b: os.fspath(p) for b, p in found.items()}}
    order_b = ["pelvis"] + [f"{b}_{s}" for s in ("r", "l") for b in ("femur", "patella", "tibia", "fibula", "talus", "calcn", "toes")]
    meshes = {b: meshes[b] for b in order_b if b in meshes}
    local = {b: local[b] for b in meshes}
    bone_body = {b: bone_body[b] for b in meshes}
    return RealAnatomy(folder.name, meshes, local, bone_body, model, mirrored,
                       None if M is None else (M, c), scan_q, js, fibula_from, sources)


def _linear():
    from kinematics.multibody.functions import Linear

    return Linear()


# --------------------------------------------------------------------------- label volume
def _scene(mesh):
    import open3d as o3d

    sc = o3d.t.geometry.RaycastingScene()
    sc.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
                     o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)))
    return sc


def _column_coverage(mesh, origin, h, shape, n_sub: int = 4) -> np.ndarray:
    """Inside fraction (shape) of every voxel: n_sub x n_sub rays per voxel column along the third axis.

    Each ray's crossings with the mesh, paired in order (entry, exit), are inside intervals; a voxel's
    fraction is the mean over its rays of the interval length within its extent along the ray, / h_z.
    A ray with an odd number of crossings (an open mesh) contributes nothing.
    """
    import open3d as o3d

    ni, nj, nk = shape
    sub = (np.arange(n_sub) + 0.5) / n_sub - 0.5
    gi, gj, si, sj = np.meshgrid(np.arange(ni), np.arange(nj), sub, sub, indexing="ij")
    col = (gi * nj + gj).ravel()
    rays = np.zeros((col.size, 6), np.float32)
    rays[:, 0] = origin[0] + (gi + si).ravel() * h[0]
    rays[:, 1] = origin[1] + (gj + sj).ravel() * h[1]
    z0 = origin[2] - 0.5 * h[2] - 0.01
    rays[:, 2] = z0
    rays[:, 5] = 1.0
    r = _scene(mesh).list_intersections(o3d.core.Tensor(rays))
    splits = r["ray_splits"].numpy().astype(np.int64)
    t = r["t_hit"].numpy().astype(float)
    ray = r["ray_ids"].numpy().astype(np.int64)
    order = np.lexsort((t, ray))
    t, ray = t[order], ray[order]
    counts = np.diff(splits)
    even = counts % 2 == 0
    keep = even[ray]
    t, ray = t[keep], ray[keep]
    start = np.r_[0, np.cumsum(counts[even])][:-1]
    # position of each hit within its ray: entries are even, exits odd
    rank = np.arange(t.size) - np.repeat(start, counts[even])
    a, b = t[rank % 2 == 0], t[rank % 2 == 1]
    rid = ray[rank % 2 == 0]
    # along the ray, voxel k spans [k h, (k + 1) h] from u = t - 0.01 (rays start half a voxel before voxel 0)
    ua, ub = (a - 0.01) / h[2], (b - 0.01) / h[2]
    ka, kb = np.floor(ua).astype(np.int64), np.floor(ub).astype(np.int64)
    cov = np.zeros((ni * nj, nk + 2))
    c = col[rid]
    w = 1.0 / n_sub**2
    same = ka == kb
    np.add.at(cov, (c[same], np.clip(ka[same], -1, nk) + 1), w * (ub - ua)[same])
    d = ~same
    np.add.at(cov, (c[d], np.clip(ka[d], -1, nk) + 1), w * (ka[d] + 1 - ua[d]))
    np.add.at(cov, (c[d], np.clip(kb[d], -1, nk) + 1), w * (ub[d] - kb[d]))
    diff = np.zeros((ni * nj, nk + 3))
    np.add.at(diff, (c[d], np.clip(ka[d] + 1, -1, nk + 1) + 1), w)
    np.add.at(diff, (c[d], np.clip(kb[d], -1, nk + 1) + 1), -w)
    cov += np.cumsum(diff, axis=1)[:, :nk + 2]
    return cov[:, 1:nk + 1].reshape(shape)


def mesh_label_volume(meshes: dict, voxel=(1e-3, 1e-3, 1e-3), noise: float = 0.0, seed: int = 0,
                      bones=None, progress: Callable[[str], None] | None = None, label_map: dict | None = None):
    """Rasterise bone meshes (scanner frame, m) into an integer label volume.

    A voxel belongs to a bone when at least half of it is inside the mesh (the analytic phantoms'
    rule, `phantoms.imaging`), the inside fraction measured exactly along 4 x 4 rays per voxel
    column (`_column_coverage`: Open3D's ``list_intersections``, about 1 s per bone at 1 mm).
    Where two bones claim a voxel the one covering more of it wins.  Segmentation noise is the
    analytic phantoms' model on the voxel-resolution signed distance
    (``scipy.ndimage.distance_transform_edt``): smooth boundary jitter, holes and islands.

    Parameters
    ----------
    meshes : dict bone -> trimesh.Trimesh (metres)
    voxel : (3,) voxel spacing, m; noise : segmentation noise level 0..1; seed : seeds the noise
    bones : subset to rasterise (default all); label_map : bone -> label (default `personalize` numbering)

    Returns
    -------
    labels : (I, J, K) int16; affine : (4, 4) voxel -> scanner MILLIMETRES; label_map : dict
    """
    from scipy import ndimage

    from .imaging import _Jitter, _add_noise, _check_voxel

    h = _check_voxel(voxel)
    if not (0.0 <= float(noise) <= 1.0):
        raise InputError("noise", f"noise level {noise} is outside 0..1")
    names = [b for b in (bones or meshes) if b in meshes]
    if not names:
        raise InputError("bones", "no bone to rasterise")
    if label_map is None:
        from .imaging import DEFAULT_LABEL_MAP

        label_map = {b: DEFAULT_LABEL_MAP[b] for b in names}
    else:
        label_map = {b: label_map[b] for b in names}
    pad = 3 * float(h.max())
    lo = np.min([meshes[b].bounds[0] for b in names], axis=0) - pad
    hi = np.max([meshes[b].bounds[1] for b in names], axis=0) + pad
    i0 = np.floor(lo / h).astype(np.int64)
    i1 = np.ceil(hi / h).astype(np.int64)
    shape = tuple(int(x) for x in (i1 - i0 + 1))
    origin = i0 * h
    labels = np.zeros(shape, np.int16)
    cover = np.zeros(shape, np.float32)
    amp = float(noise) * float(np.mean(h))
    for bi, b in enumerate(names):
        if progress:
            progress(b)
        m = meshes[b]
        a = np.clip(np.floor((m.bounds[0] - pad) / h).astype(np.int64) - i0, 0, shape)
        e = np.clip(np.ceil((m.bounds[1] + pad) / h).astype(np.int64) - i0 + 1, 0, shape)
        sh = tuple(int(x) for x in (e - a))
        frac = _column_coverage(m, origin + a * h, h, sh)
        inside = frac >= 0.5
        if noise > 0:
            d = (ndimage.distance_transform_edt(~inside, sampling=h)
                 - ndimage.distance_transform_edt(inside, sampling=h)).astype(np.float32)
            rng = np.random.default_rng([int(seed), bi, 11])
            jit = _Jitter(rng)
            band = np.nonzero(np.abs(d) < amp + 1.5 * float(h.max()))
            p = origin + (a + np.column_stack(band)) * h
            inside[band] = (d[band] + amp * jit(p)) <= 0
            _add_noise(inside, d, h, float(noise), rng)
            frac = np.where(inside, np.maximum(frac, 0.5), frac)
        region = labels[a[0]:e[0], a[1]:e[1], a[2]:e[2]]
        creg = cover[a[0]:e[0], a[1]:e[1], a[2]:e[2]]
        win = inside & ((region == 0) | (frac > creg))
        region[win] = label_map[b]
        creg[win] = frac[win]
    affine = np.eye(4)
    affine[:3, :3] = np.diag(h * 1000.0)
    affine[:3, 3] = origin * 1000.0
    return labels, affine, label_map
