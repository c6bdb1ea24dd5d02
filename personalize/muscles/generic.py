"""The generic musculoskeletal model the muscles come from: OpenSim's gait2392 (Delp et al. 1990; Anderson & Pandy
1999), read at run time from the user's copy of the opensim-models repository (Apache-2.0), never shipped.

Where the model is found (`generic_model_path`): the path given (``--gait2392 FILE``), else the environment
variable ``PERSONALIZE_GAIT2392``, else ``$PERSONALIZE_SHARED_DATA/opensim_gait2392/gait2392_thelen2003muscle.osim``,
else ``../shared/data/opensim_gait2392/...`` beside the repository.  Its bone meshes are the VTP files of
``Geometry/`` beside the model (ASCII VTK PolyData, metres, each in its body's frame).

Frames: gait2392's bodies (``pelvis``, ``femur_r``, ``tibia_r``, ``talus_r``, ``calcn_r``, ``toes_r`` and left;
X anterior, Y superior, Z right).  Unlike the personalised model, the femur's origin is the hip centre and the
tibia's the knee (the planar knee's translations are splines of ``knee_angle``).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from lowerlimb.errors import InputError

__all__ = ["GENERIC_ENV", "GENERIC_FILE", "LEG_BODIES", "GenericModel", "generic_model_path", "load_generic_model",
           "joint_points", "zero_state", "body_poses", "read_vtp", "generic_landmarks", "side_free", "LANDMARK_BONES",
           "anatomical_points"]

#: environment variable naming the generic model file
GENERIC_ENV = "PERSONALIZE_GAIT2392"
#: the generic model's file inside the shared data folder
GENERIC_FILE = Path("opensim_gait2392") / "gait2392_thelen2003muscle.osim"
#: meshes left out of the registration surfaces: the sacrum (a subject's pelvis is often the hip bones alone)
LEFT_OUT_MESHES = ("sacrum.vtp",)
#: body base names that carry leg muscles (the trunk muscles ride on ``torso``, which the personalised model lacks)
LEG_BODIES = ("pelvis", "femur", "tibia", "talus", "calcn", "toes")
#: right-side bone (landmark detector's name) -> the gait2392 body it rides on; the fibula is a mesh of ``tibia_r``
LANDMARK_BONES = {"femur_r": "femur_r", "tibia_r": "tibia_r", "fibula_r": "tibia_r", "talus_r": "talus_r",
                  "calcn_r": "calcn_r", "toes_r": "toes_r"}


def generic_model_path(path: str | os.PathLike | None = None, *, required: bool = True) -> Path | None:
    """The generic gait2392 model file (see the module docstring for the search order).

    Raises
    ------
    InputError
        `required` and no file found (or the given / environment path is not a file).
    """
    if path is not None or os.environ.get(GENERIC_ENV):
        p = Path(path if path is not None else os.environ[GENERIC_ENV])
        if p.is_file():
            return p
        raise InputError(p, "the generic gait2392 model (.osim) is not there"
                            + ("" if path is not None else f" (environment variable {GENERIC_ENV})"))
    roots = []
    if os.environ.get("PERSONALIZE_SHARED_DATA"):
        roots.append(Path(os.environ["PERSONALIZE_SHARED_DATA"]))
    roots.append(Path(__file__).resolve().parents[3] / "shared" / "data")
    for r in roots:
        if (r / GENERIC_FILE).is_file():
            return r / GENERIC_FILE
    if required:
        raise InputError(GENERIC_FILE.name, "the generic gait2392 model was not found: give --gait2392 FILE or set "
                                            f"{GENERIC_ENV} (gait2392_thelen2003muscle.osim of opensim-models)")
    return None


def read_vtp(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (n, 3) and triangles (m, 3) of an ASCII VTK PolyData file (polygons fanned into triangles).

    Raises
    ------
    InputError
        Not an ASCII PolyData file.
    """
    from defusedxml import ElementTree

    try:
        root = ElementTree.parse(os.fspath(path)).getroot()
        piece = root.find("PolyData/Piece")
        pts = piece.find("Points/DataArray")
        polys = piece.find("Polys")
        arrays = {a.get("Name"): a for a in polys.findall("DataArray")}
        if any(a.get("format", "ascii") != "ascii" for a in (pts, *arrays.values())):
            raise ValueError("binary data arrays are not read")
        V = np.array(pts.text.split(), float).reshape(-1, 3)
        conn = np.array(arrays["connectivity"].text.split(), int)
        offs = np.array(arrays["offsets"].text.split(), int)
    except (AttributeError, KeyError, ValueError, OSError, ElementTree.ParseError) as exc:
        raise InputError(path, f"not an ASCII VTK PolyData mesh ({exc})") from None
    tris, start = [], 0
    for end in offs:
        f = conn[start:end]
        tris.extend((f[0], f[k], f[k + 1]) for k in range(1, len(f) - 1))
        start = end
    return V, np.asarray(tris, int).reshape(-1, 3)


@dataclass(frozen=True, eq=False)
class GenericModel:
    """gait2392 read once: the OpenSim model, its leg bodies' meshes and joint points.

    path : the .osim file
    model : opensim.Model (initialised; its default state has every coordinate at zero)
    meshes : body -> trimesh.Trimesh, the body's bone meshes merged (metres, body frame; not `LEFT_OUT_MESHES`)
    joint_points : body -> {joint name: (3,) m}, where each joint the body takes part in is, in the body's frame, at
        the all-zero pose (`joint_points`; the knee's includes its translation at ``knee_angle = 0``)
    poses : body -> 4x4 pose in ground at the all-zero pose (`body_poses`)
    landmarks : body -> {landmark name (`side_free`): (3,) m, body frame}, the repository's detectors on gait2392's
        own bones (`generic_landmarks`)
    """

    path: Path
    model: object
    meshes: dict
    joint_points: dict
    poses: dict
    landmarks: dict = None

    def muscles(self) -> list:
        """The generic model's muscles whose path points all ride on leg bodies (`LEG_BODIES`)."""
        out = []
        ms = self.model.getMuscles()
        for i in range(ms.getSize()):
            mu = ms.get(i)
            pps = mu.getGeometryPath().getPathPointSet()
            bodies = {pps.get(j).getBodyName() for j in range(pps.getSize())}
            if all(b.rsplit("_", 1)[0] in LEG_BODIES for b in bodies):
                out.append(mu)
        return out


@lru_cache(maxsize=4)
def _load(path: str, mtime: float) -> GenericModel:
    import trimesh

    from kinematics.io.opensim_io import import_opensim

    osim = import_opensim()
    m = osim.Model(path)
    m.initSystem()
    geometry = Path(path).parent / "Geometry"
    meshes, files = {}, {}
    bodies = m.getBodySet()
    for i in range(bodies.getSize()):
        b = bodies.get(i)
        if b.getName().rsplit("_", 1)[0] not in LEG_BODIES:
            continue
        parts = []
        for k in range(b.getPropertyByName("attached_geometry").size()):
            g = osim.Mesh.safeDownCast(b.get_attached_geometry(k))
            if g is None or g.get_mesh_file() in LEFT_OUT_MESHES:
                continue
            f = geometry / g.get_mesh_file()
            if not f.is_file():
                raise InputError(f, f"mesh of gait2392's body {b.getName()} missing (Geometry/ beside the model)")
            V, F = read_vtp(f)
            sc = np.array([g.get_scale_factors().get(j) for j in range(3)])
            parts.append(trimesh.Trimesh(V * sc, F, process=True))
            files[g.get_mesh_file()] = (b.getName(), parts[-1])
        if parts:
            meshes[b.getName()] = trimesh.util.concatenate(parts)
    state = zero_state(m)
    return GenericModel(Path(path), m, meshes, joint_points(m, state), body_poses(m, state),
                        generic_landmarks(meshes, files))


def side_free(name: str, body: str) -> str:
    """A landmark's name with its side marker dropped on a sided body (``RKNE`` on ``femur_r`` -> ``KNE``), so
    that a right and a left bone's landmarks share names; the pelvis's names (``RASI``, ``LASI``) are kept."""
    import re

    if body.endswith(("_r", "_l")) and re.fullmatch(r"[RL][A-Z0-9]{3}", name):
        return name[1:]
    return name


def _closest_on_first(p, d, q, e):
    """The point of line (p, d) closest to line (q, e), or None for parallel lines."""
    d, e = d / np.linalg.norm(d), e / np.linalg.norm(e)
    b = float(d @ e)
    if 1.0 - b * b < 1e-9:
        return None
    w = p - q
    return p + d * ((b * (e @ w) - d @ w) / (1.0 - b * b))


def anatomical_points(res) -> dict:
    """name -> (3,) m: a bone's detected landmarks (`personalize.landmarks.BoneLandmarks`) and the points its axes
    define: ``neck_shaft_point``, the femoral neck axis's point nearest the shaft axis (with the head centre it
    fixes the neck's direction: anteversion and neck-shaft angle, which no surface landmark does)."""
    out = {n: np.asarray(lm.position, float) for n, lm in res.landmarks.items()}
    ax = res.axes
    if "neck_axis" in ax and "shaft_axis" in ax:
        x = _closest_on_first(*(np.asarray(v, float) for v in (ax["neck_axis"].point, ax["neck_axis"].direction,
                                                               ax["shaft_axis"].point, ax["shaft_axis"].direction)))
        if x is not None:
            out["neck_shaft_point"] = x
    return out


def generic_landmarks(meshes: dict, files: dict) -> dict:
    """body -> {name: (3,) m}: `personalize.landmarks.detect_landmarks` on gait2392's right bones and pelvis (body
    frames, the tibia and fibula meshes of ``tibia_r`` apart), names `side_free`; the left bodies' from the right
    ones mirrored, ``z -> -z`` (gait2392's left meshes are the right ones mirrored).

    meshes : body -> merged trimesh (`GenericModel.meshes`); files : mesh file -> (body, trimesh)
    """
    from personalize.landmarks import detect_landmarks

    bones = {"pelvis": meshes["pelvis"]} if "pelvis" in meshes else {}
    for f, (body, mesh) in files.items():
        if body.endswith("_r"):
            bones["fibula_r" if "fibula" in f else body] = mesh
    ls = detect_landmarks(bones, trust_names=True)
    out: dict = {}
    for bone, res in ls.bones.items():
        body = "pelvis" if bone == "pelvis" else LANDMARK_BONES.get(bone)
        if body is None:
            continue
        for n, x in anatomical_points(res).items():
            out.setdefault(body, {})[side_free(n, body)] = x
            if body != "pelvis":
                out.setdefault(body[:-1] + "l", {})[side_free(n, body)] = x * [1.0, 1.0, -1.0]
    return out


def zero_state(model):
    """A realised (position stage) state of an initialised opensim model with every coordinate at zero (the
    coupling constraints not enforced)."""
    state = model.initSystem()
    cs = model.getCoordinateSet()
    for i in range(cs.getSize()):
        cs.get(i).setValue(state, 0.0, False)
    model.realizePosition(state)
    return state


def joint_points(model, state) -> dict:
    """body -> {joint: (3,) m}: each joint's centre (the origin of its child-side frame) in the frames of its parent
    and child bodies, at `state`."""
    from kinematics.io.opensim_io import import_opensim

    osim = import_opensim()
    out: dict = {}
    js = model.getJointSet()
    for i in range(js.getSize()):
        j = js.get(i)
        parent, child = j.getParentFrame().findBaseFrame(), j.getChildFrame().findBaseFrame()
        for body in (parent, child):
            x = j.getChildFrame().findStationLocationInAnotherFrame(state, osim.Vec3(0, 0, 0), body)
            out.setdefault(body.getName(), {})[j.getName()] = np.array([x.get(k) for k in range(3)])
    return out


def body_poses(model, state) -> dict:
    """body -> 4x4 pose in ground at `state` (x_ground = T @ [x_body, 1])."""
    out = {}
    bs = model.getBodySet()
    for i in range(bs.getSize()):
        b = bs.get(i)
        X = b.getTransformInGround(state)
        R, p = X.R(), X.p()
        T = np.eye(4)
        T[:3, :3] = [[R.get(r, c) for c in range(3)] for r in range(3)]
        T[:3, 3] = [p.get(k) for k in range(3)]
        out[b.getName()] = T
    return out


def load_generic_model(path: str | os.PathLike | None = None) -> GenericModel:
    """The generic model (`generic_model_path`), loaded once per file."""
    p = generic_model_path(path)
    from kinematics.io.opensim_io import check_osim_file

    check_osim_file(p)
    return _load(os.fspath(p.resolve()), p.stat().st_mtime)
