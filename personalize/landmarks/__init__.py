"""Bone landmark detectors (issue F3): one module per bone, `detect_landmarks` for a set.

Bones are processed in an order that lets each detector use its already
detected neighbours as cues (femur -> pelvis -> tibia/fibula -> patella ->
talus -> calcaneus -> toes); every detector also works alone, with a
``low_confidence`` flag where the missing neighbour mattered.
"""
from __future__ import annotations

from typing import Callable, Mapping

from lowerlimb.errors import FitError, InputError
from lowerlimb.bones import BONE_NAMES, canonical_bone_name, side_of
from personalize.io import MESH_SUFFIXES, POINT_SUFFIXES

from .common import (FLAG_LOW_CONFIDENCE, FLAG_NAME_MISMATCH, FLAG_NOT_CLOSED, FLAG_SIDE_MISMATCH, Axis,
                     BoneLandmarks, Landmark, LandmarkSet)
from .surface import Surface, as_surface, even_sampling
from .femur import detect_femur
from .foot import detect_calcn, detect_toes
from .patella import detect_patella
from .pelvis import detect_pelvis
from .talus import detect_talus
from .tibia import detect_fibula, detect_tibia, malleolar_markers, tibia_surface

__all__ = ["Axis", "BoneLandmarks", "Landmark", "LandmarkSet", "Surface", "as_surface", "detect_landmarks",
           "name_problems",
           "joints_from_landmarks", "detect_femur", "detect_tibia", "detect_fibula", "detect_talus",
           "detect_calcn", "detect_toes", "detect_pelvis", "detect_patella"]


def joints_from_landmarks(ls: LandmarkSet):
    """Joint frames from detected landmarks; see `personalize.frames.joints_from_landmarks`."""
    from personalize.frames import joints_from_landmarks as _j

    return _j(ls)


def _check_side(res: BoneLandmarks, name: str) -> None:
    expected = side_of(name)
    if expected and res.side and res.side != expected:
        res.flag(FLAG_SIDE_MISMATCH, f"{name}: the bone's shape is a {'right' if res.side == 'r' else 'left'} bone")
        res.flag(FLAG_LOW_CONFIDENCE)


def name_problems(ls: LandmarkSet) -> dict[str, str]:
    """Bones whose shape says they are another bone or the other side: bone -> the detector's reason.

    From the detectors' `FLAG_NAME_MISMATCH` (e.g. no femoral head on a
    "femur", a femoral head on a "tibia") and `FLAG_SIDE_MISMATCH` (the
    chirality of the bone's anatomical axes is the other side's).
    """
    out: dict[str, str] = {}
    for name, res in ls.bones.items():
        why = [n for n in res.notes if (FLAG_NAME_MISMATCH in res.flags and "is this mesh a" in n)
               or (FLAG_SIDE_MISMATCH in res.flags and "the bone's shape is a" in n)]
        if why:
            out[name] = "; ".join(w.removeprefix(f"{name}: ") for w in why)
    return out


def _refuse_names(ls: LandmarkSet, bones: Mapping[str, object]) -> None:
    problems = name_problems(ls)
    if not problems:
        return
    name = next(b for b in BONE_NAMES if b in problems)
    src = next((getattr(v, "source", None) for k, v in bones.items() if canonical_bone_name(str(k)) == name), None)
    volume = src is not None and not str(src).lower().endswith(MESH_SUFFIXES + POINT_SUFFIXES)
    more = [b for b in problems if b != name]
    raise InputError(src, f"{name}: {problems[name]}"
                     + (f" (also {', '.join(more)})" if more else "")
                     + ("; check the label map" if volume else "; check the file name")
                     + " (personalize bones --trust-names uses the bones as named)")


def detect_landmarks(bones: Mapping[str, object], progress: Callable[[str], None] | None = None, *,
                     trust_names: bool = False) -> LandmarkSet:
    """Detect landmarks, axes and frames on every recognised bone.

    Parameters
    ----------
    bones : mapping name -> surface
        Bone name (canonical or alias, e.g. ``femur_r``, ``pelvis_no_sacrum``)
        -> `personalize.surfaces.BoneSurface`, `trimesh.Trimesh` (metres) or
        `Surface`.
    progress : callable, optional
        Called with each bone name when it is done.
    trust_names : bool
        Use a bone whose shape says it is another bone or the other side
        (`name_problems`) under its name, flagged; by default such a set is
        refused.

    Returns
    -------
    LandmarkSet
        Per-bone results (input frame, metres); ``missing`` lists the bones
        absent on the sides present, ``rejected`` the inputs that could not
        be used (with the reason).

    Raises
    ------
    InputError
        If no recognised bone is given, or (unless `trust_names`) a bone's
        shape contradicts its name or side.
    """
    surf: dict[str, Surface] = {}
    sampling_notes: dict[str, str] = {}
    ls = LandmarkSet()
    todo: dict[str, tuple[str, object]] = {}
    for key, obj in bones.items():
        name = canonical_bone_name(str(key))
        if name is None:
            ls.rejected[str(key)] = "not a recognised bone name"
            continue
        if name not in todo:
            todo[name] = (str(key), obj)

    def prepare(name):
        key, obj = todo[name]
        try:
            obj, note = even_sampling(obj, name)
            return key, as_surface(obj, name), note, None
        except InputError as exc:
            return key, None, None, exc.problem

    # the bones' sampling and surface arrays are independent: two threads (numpy and trimesh release the GIL)
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=2) as pool:
        prepared = dict(zip(todo, pool.map(prepare, list(todo))))
    for name, (key, s_, note, problem) in prepared.items():
        if problem is not None:
            ls.rejected[key] = problem
            continue
        surf[name] = s_
        if note:
            sampling_notes[name] = note
    if not surf:
        raise InputError(None, "no recognisable bone surfaces (expected names like "
                               + ", ".join(BONE_NAMES[:4]) + ", ...)")
    sides = {n[-1] for n in surf if n[-2:] in ("_r", "_l")}
    ls.missing = [b for b in BONE_NAMES if b not in surf and (b == "pelvis" or b[-1] in sides)]

    def run(name, fn):
        try:
            res = fn()
        except FitError as exc:
            res = BoneLandmarks(bone=name, side=side_of(name))
            res.flag(FLAG_LOW_CONFIDENCE, f"{name}: detection failed ({exc})")
        if name in sampling_notes:
            res.notes.append(sampling_notes[name])
        if not surf[name].closed:
            res.flag(FLAG_NOT_CLOSED, f"{name}: surface is not closed; volume-based quantities approximate")
        _check_side(res, name)
        ls.bones[name] = res
        if progress is not None:
            progress(name)
        return res

    def thigh_and_pelvis():
        for s in ("r", "l"):
            if f"femur_{s}" in surf:
                run(f"femur_{s}", lambda s=s: detect_femur(surf[f"femur_{s}"], f"femur_{s}"))
        if "pelvis" in surf:
            ant = None
            for s in ("r", "l"):
                f = ls.bones.get(f"femur_{s}")
                if f is not None and "anatomical" in f.frames and FLAG_LOW_CONFIDENCE not in f.flags:
                    ant = f.frames["anatomical"]["rotation"][:, 0]
                    break
            run("pelvis", lambda: detect_pelvis(surf["pelvis"], "pelvis", anterior_hint=ant))
        for s in ("r", "l"):
            pname = f"patella_{s}"
            if pname in surf:
                fem = ls.bones.get(f"femur_{s}")
                prox = fem.frames["anatomical"]["rotation"][:, 1] if fem is not None and "anatomical" in fem.frames \
                    else None
                run(pname, lambda s=s, pname=pname, prox=prox: detect_patella(
                    surf[pname], pname, femur=surf.get(f"femur_{s}"), proximal_hint=prox))

    def shank_and_foot():
        for s in ("r", "l"):
            _shank_and_foot(s, surf, ls, run)

    # the thigh-pelvis chain and the shank-foot chain use each other's surfaces, never their results: two
    # threads (numpy releases the GIL), each chain in its own fixed order, so the results are the sequential ones
    with ThreadPoolExecutor(max_workers=2) as pool:
        for job in [pool.submit(thigh_and_pelvis), pool.submit(shank_and_foot)]:
            job.result()
    order = [f"femur_{s}" for s in "rl"] + ["pelvis"] + [f"{b}_{s}" for s in "rl" for b in
                                                          ("tibia", "fibula", "patella", "talus", "calcn", "toes")]
    ls.bones = {b: ls.bones[b] for b in sorted(ls.bones, key=lambda b: order.index(b) if b in order else len(order))}
    for s in ("r", "l"):
        _tibia_isb(ls, s)
    if not trust_names:
        _refuse_names(ls, bones)
    return ls



def _shank_and_foot(s: str, surf: dict, ls: LandmarkSet, run) -> None:
    """Tibia, fibula, talus, calcaneus and toes of side `s`, in that order (each uses the ones before)."""
    tname, fname = f"tibia_{s}", f"fibula_{s}"
    fib_comp = None
    if tname in surf:
        holder = {}

        def _tib(s=s, tname=tname, fname=fname, holder=holder):
            r, fc = detect_tibia(surf[tname], tname, fibula=surf.get(fname), femur=surf.get(f"femur_{s}"),
                                 talus=surf.get(f"talus_{s}"))
            holder["fc"] = fc
            return r
        run(tname, _tib)
        fib_comp = holder.get("fc")
    tib = ls.bones.get(tname)
    if fname in surf:
        run(fname, lambda s=s, fname=fname, tib=tib: detect_fibula(surf[fname], fname, tib))
    elif fib_comp is not None and tib is not None:
        res = detect_fibula(fib_comp, fname, tib)
        res.notes.append(f"{fname}: taken from the second component of {tname}")
        ls.bones[fname] = res
        if fname in ls.missing:
            ls.missing.remove(fname)
    up = right = None
    if tib is not None and "anatomical" in tib.frames:
        R = tib.frames["anatomical"]["rotation"]
        up, right = R[:, 1], R[:, 2]
    aname = f"talus_{s}"
    if aname in surf:
        tib_s = tibia_surface(surf[tname]) if tname in surf else None
        run(aname, lambda s=s, aname=aname, tib_s=tib_s, up=up, right=right: detect_talus(
            surf[aname], aname, tibia=tib_s, calcaneus=surf.get(f"calcn_{s}"), right_hint=right, up_hint=up))
    tal = ls.bones.get(aname)
    fib_s = surf.get(fname, fib_comp)
    if tal is not None and "ankle_axis" in tal.axes and tib is not None and fname in ls.bones \
            and fib_s is not None:
        malleolar_markers(tib_s, fib_s, tib, ls.bones[fname], tal.axes["ankle_axis"].direction)
    if tal is not None and "anatomical" in tal.frames:
        R = tal.frames["anatomical"]["rotation"]
        up = R[:, 1] if up is None else up
        right = R[:, 2] if right is None else right
    cname = f"calcn_{s}"
    if cname in surf:
        run(cname, lambda s=s, cname=cname, up=up, right=right: detect_calcn(
            surf[cname], cname, up_hint=up, right_hint=right, talus=surf.get(aname)))
    oname = f"toes_{s}"
    if oname in surf:
        run(oname, lambda s=s, oname=oname: detect_toes(surf[oname], oname, ls.bones.get(f"calcn_{s}")))


def _tibia_isb(ls: LandmarkSet, s: str) -> None:
    """Tibial ISB frame from the malleoli (tibia + fibula) and the knee centre (femur or plateau).

    Origin midway between the malleoli, Y towards the knee centre, Z towards
    the right-hand malleolus (made orthogonal to Y), X = Y x Z.
    """
    tib, fib, fem = ls.bones.get(f"tibia_{s}"), ls.bones.get(f"fibula_{s}"), ls.bones.get(f"femur_{s}")
    if tib is None or fib is None or "medial_malleolus_tip" not in tib.landmarks or "lateral_malleolus_tip" not in fib.landmarks:
        return
    from personalize.frames import frame_yz

    mma, ank = tib.landmarks["medial_malleolus_tip"].position, fib.landmarks["lateral_malleolus_tip"].position
    mal = 0.5 * (mma + ank)
    if fem is not None and "intercondylar_midpoint" in fem.landmarks:
        knee = fem.landmarks["intercondylar_midpoint"].position
    elif "plateau_centre" in tib.landmarks:
        knee = tib.landmarks["plateau_centre"].position
    else:
        return
    right = ank - mma if s == "r" else mma - ank
    tib.frames["isb"] = {"origin": mal, "rotation": frame_yz(knee - mal, right)}
