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
from lowerlimb.tasks import run_tasks
from personalize.io import MESH_SUFFIXES, POINT_SUFFIXES

from .common import (FLAG_LOW_CONFIDENCE, FLAG_NAME_MISMATCH, FLAG_NOT_CLOSED, FLAG_SIDE_MISMATCH, FLAG_TRUNCATED, Axis,
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
            surf[name] = as_surface(obj, name)
        except InputError as exc:
            ls.rejected[key] = exc.problem
            return
        if note:
            sampling_notes[name] = note

    def run(name, fn):
        if name not in surf:
            return None
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

    # three threads for two cores: the detectors' small-array Python work holds the GIL while another
    # thread's large numpy calls do not (ICL_MRI median 1.30-1.42 s against 1.42-1.53 s with the former
    # two fixed chains, measured alternately)
    run_tasks(_detection_graph(list(todo), prepare, run, surf, ls), workers=3)
    if not surf:
        raise InputError(None, "no recognisable bone surfaces (expected names like "
                               + ", ".join(BONE_NAMES[:4]) + ", ...)")
    sides = {n[-1] for n in surf if n[-2:] in ("_r", "_l")}
    ls.missing = [b for b in BONE_NAMES if b not in surf and b not in ls.bones and (b == "pelvis" or b[-1] in sides)]
    order = [f"femur_{s}" for s in "rl"] + ["pelvis"] + [f"{b}_{s}" for s in "rl" for b in
                                                          ("tibia", "fibula", "patella", "talus", "calcn", "toes")]
    ls.bones = {b: ls.bones[b] for b in sorted(ls.bones, key=lambda b: order.index(b) if b in order else len(order))}
    ls.rejected = {k: ls.rejected[k] for k in [str(k) for k in bones] if k in ls.rejected}
    for s in ("r", "l"):
        _tibia_isb(ls, s)
    if not trust_names:
        _refuse_names(ls, bones)
    return ls


def _detection_graph(names: list[str], prepare, run, surf: dict, ls: LandmarkSet) -> dict:
    """The tasks of `detect_landmarks`: each bone's surface prepared, then its detector once the surfaces
    and the neighbours' results it uses are there (`lowerlimb.tasks.run_tasks`).

    A detector reads its neighbours' surfaces and, for hints, the results of the bones before it in its
    chain (femur -> pelvis, patella; tibia -> fibula, talus -> calcaneus -> toes); nothing else, so any
    order the dependencies allow gives the same landmarks.  Listed longest chain first (tibia, talus,
    calcaneus wait for each other; the femur and the pelvis do not): the order in which the threads
    take ready tasks.
    """
    present = set(names)
    g: dict[str, tuple[tuple[str, ...], Callable]] = {}

    def add(task, deps, fn):
        g[task] = (tuple(deps), fn)

    def prep(b):
        if b in present and f"prep {b}" not in g:
            add(f"prep {b}", (), lambda b=b: prepare(b))

    for s in ("r", "l"):
        fem, tib, fib, tal, cal, toe = (f"{b}_{s}" for b in ("femur", "tibia", "fibula", "talus", "calcn", "toes"))
        for b in (tib, fem, tal, fib):
            prep(b)
        shank: dict = {}
        if tib in present:
            def _tib(tib=tib, fib=fib, fem=fem, tal=tal, shank=shank):
                def fn():
                    r, shank["fibula_component"] = detect_tibia(surf[tib], tib, fibula=surf.get(fib),
                                                                femur=surf.get(fem), talus=surf.get(tal))
                    return r
                run(tib, fn)
            add(tib, (f"prep {tib}", f"prep {fib}", f"prep {fem}", f"prep {tal}"), _tib)
        prep(cal)

        def _talus(tib=tib, tal=tal, cal=cal, shank=shank):
            up, right = _up_right(ls, tib)
            shank["tibia_surface"] = tibia_surface(surf[tib]) if tib in surf else None
            run(tal, lambda: detect_talus(surf[tal], tal, tibia=shank["tibia_surface"], calcaneus=surf.get(cal),
                                          right_hint=right, up_hint=up))
        if tal in present:
            add(tal, (f"prep {tal}", f"prep {cal}", f"prep {tib}", tib), _talus)

        def _fibula(tib=tib, fib=fib, shank=shank):
            t = ls.bones.get(tib)
            if fib in surf:
                run(fib, lambda: detect_fibula(surf[fib], fib, t))
            elif shank.get("fibula_component") is not None and t is not None:
                res = detect_fibula(shank["fibula_component"], fib, t)
                res.notes.append(f"{fib}: taken from the second component of {tib}")
                ls.bones[fib] = res
        add(fib, (f"prep {fib}", tib), _fibula)

        def _malleoli(tib=tib, fib=fib, tal=tal, shank=shank):
            t, a = ls.bones.get(tib), ls.bones.get(tal)
            fib_s = surf.get(fib, shank.get("fibula_component"))
            if a is not None and "ankle_axis" in a.axes and t is not None and fib in ls.bones and fib_s is not None:
                malleolar_markers(shank.get("tibia_surface"), fib_s, t, ls.bones[fib], a.axes["ankle_axis"].direction)
        add(f"malleoli {s}", (tib, fib, tal), _malleoli)

        def _calcn(tib=tib, tal=tal, cal=cal, toe=toe):
            up, right = _up_right(ls, tib, tal)
            run(cal, lambda: detect_calcn(surf[cal], cal, up_hint=up, right_hint=right, talus=surf.get(tal),
                                          toes=surf.get(toe)))
        if cal in present:
            add(cal, (f"prep {cal}", f"prep {tal}", f"prep {toe}", tib, tal), _calcn)
        if fem in present:
            add(fem, (f"prep {fem}",), lambda fem=fem: run(fem, lambda: detect_femur(surf[fem], fem)))
        prep(toe)
        if toe in present:
            add(toe, (f"prep {toe}", cal), lambda toe=toe, cal=cal: run(
                toe, lambda: detect_toes(surf[toe], toe, ls.bones.get(cal))))
    prep("pelvis")

    def _pelvis():
        # a confident femur's anterior first; else a whole one flagged for something else (its knee estimates
        # disagreeing, say): its condyles still face forward, and the pelvis' own cue (the symphysis 2-12 mm in
        # front of the hip centres on the real sets) is the weaker one
        femurs = [f for f in (ls.bones.get(f"femur_{s}") for s in ("r", "l")) if f is not None and "anatomical" in f.frames]
        ranked = ([f for f in femurs if FLAG_LOW_CONFIDENCE not in f.flags]
                  + [f for f in femurs if FLAG_LOW_CONFIDENCE in f.flags and FLAG_TRUNCATED not in f.flags])
        ant = ranked[0].frames["anatomical"]["rotation"][:, 0] if ranked else None
        run("pelvis", lambda: detect_pelvis(surf["pelvis"], "pelvis", anterior_hint=ant))
    if "pelvis" in present:
        add("pelvis", ("prep pelvis", "femur_r", "femur_l"), _pelvis)
    for s in ("r", "l"):
        fem, pat = f"femur_{s}", f"patella_{s}"
        prep(pat)

        def _patella(fem=fem, pat=pat):
            f = ls.bones.get(fem)
            prox = f.frames["anatomical"]["rotation"][:, 1] if f is not None and "anatomical" in f.frames else None
            run(pat, lambda: detect_patella(surf[pat], pat, femur=surf.get(fem), proximal_hint=prox))
        if pat in present:
            add(pat, (f"prep {pat}", f"prep {fem}", fem), _patella)
    for b in names:
        prep(b)
    return g


def _up_right(ls: LandmarkSet, *bones: str) -> tuple:
    """The superior (Y) and right (Z) axes of the first of `bones` detected with an anatomical frame, the
    detectors' orientation hints (None, None without one)."""
    for b in bones:
        res = ls.bones.get(b)
        if res is not None and "anatomical" in res.frames:
            R = res.frames["anatomical"]["rotation"]
            return R[:, 1], R[:, 2]
    return None, None


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
