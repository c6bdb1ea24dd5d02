"""Knee models compared by marker IK: the experiments of Pronost et al. (2010), section 4.1.

Three knee models share one skeleton and differ only in how the knee's six
coordinates (flexion ``a1``, ab/adduction ``a2``, axial rotation ``a3``;
translations ``T = (tx, ty, tz)`` in the parent (femur) frame) are constrained:

* ``1DOF`` hinge (`HingeKnee`): ``a2, a3, T`` constant, flexion free;
* ``3DOF`` planar spline knee, gait2392 style (`PlanarSplineKnee`): ``a2, a3,
  tz`` constant, the sagittal translations natural cubic splines of flexion,
  ``tx = Sx(a1)``, ``ty = Sy(a1)`` (Yamaguchi & Zajac 1989; OpenSim gait2392);
* ``3+DOF`` correlative knee (`CorrelativeKnee`): three free rotations and the
  translations the linear law of seed eq. (1), ``T = C a + c0``.

Every constraint goes through the engine's one mechanism: constant and linear
relations are rows of `kinematics.multibody.coupling.LinearCoupling` (``C q = d``,
eliminated in IK by the null-space parametrisation ``q = q_p + N z``), the
splines are `CoordinateCoupler` dependents whose chain rule
``dq_dep/dz = S'(a1) dq_a1/dz`` enters IK's Jacobian.

Protocol (seed 3.2 and 4.1): a free six-DOF knee is tracked by IK on training
trials; its per-frame coordinates give the laws (multiple linear regression),
the splines and the constants (all least squares on the same frames).  The
models are then compared by IK on held-out trials.  The score of a trial is
the seed's: the sum over frames of the frame's RMS distance between measured
and model markers (not normalised by frames or markers, metres), reported with
the mean frame RMS.

Two IK protocols (`TrackingProtocol`):

* the seed's (`seed_protocol`, section 3.2: "an IK solver driven by the
  positions of the seven markers", equal weights): a one-leg model
  (`leg_model`) that keeps only the bodies the seven markers observe (pelvis,
  thigh, shank), the pelvis rotations locked so that pelvis translation and
  hip rotations are exactly the thigh's six free coordinates, the other leg
  and the foot removed (no tracked marker sees them);
* the whole-body protocol (`whole_body_protocol`): every skin marker of the
  pelvis and both legs, both knees learnt and compared.

Units: radians, metres.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable, Iterable, Mapping, Sequence

import numpy as np

from kinematics.mechanisms.correlative import CorrelativeLaw
from kinematics.mechanisms.correlative_fit import fit_law
from personalize.presentation.correlative_tables import TextTable
from kinematics.multibody.coupling import CoordinateCoupler, LinearCoupling
from kinematics.multibody.coupling import LinearInequalities
from lowerlimb.errors import FitError, InputError
from kinematics.algorithms.fk import marker_jacobian
from kinematics.multibody.functions import NaturalCubicSpline
from kinematics.algorithms.coordinate_map import coordinate_map
from kinematics.algorithms.ik import IKResult, solve_ik
from kinematics.io.markers import MarkerTrial
from kinematics.multibody.model import GROUND, Model

__all__ = [
    "knee_rotations", "knee_translations", "knee_coordinates",
    "HingeKnee", "PlanarSplineKnee", "CorrelativeKnee", "FreeKnee", "KneeKinematics",
    "strip_knee_constraints", "with_knees", "free_knee_model",
    "knee_kinematics", "fit_hinge_knee", "fit_planar_spline_knee", "fit_correlative_knee", "fit_spline_basis",
    "TrialScore", "score_trial", "track", "summarize", "reduction",
    "tracking_table", "TrainedKnees", "train_knees", "compare_knees", "score_results", "VARIANTS",
    "fit_knee_models", "select_frames", "sub_motion_knees", "compare_knees_by_sub_motion",
    "knee_coordinate_errors", "SEED_MARKERS", "leg_model", "undetermined_coordinates", "TrackingProtocol", "seed_protocol", "whole_body_protocol",
]

#: Column names of the seed's Table 3 (hinge, planar spline, correlative)
VARIANTS = ("1DOF", "3DOF", "3+DOF")

#: The seed's seven right-leg markers (section 3.1) -> their analogues in a Plug-in-Gait marker set
#: with medial knee/ankle markers (KNEM, ANKM), a proximal antero-lateral thigh marker (THIP) and a
#: distal medial tibia skin marker (TIBM3) (the motion phantoms' labels).  Epicondyles and malleoli
#: are the same landmarks; the greater trochanter, tibial tuberosity and fibular head carry no marker
#: in that set, so the most proximal thigh marker and the two remaining shank skin markers stand in
#: (two markers on the femur with the epicondyles, four on the shank, as the seed's set).
SEED_MARKERS = {"RGT": "RTHIP", "RLFE": "RKNE", "RMFE": "RKNEM", "RTT": "RTIBM3", "RFH": "RTIB",
                "RLATMAL": "RANK", "RMEDMAL": "RANKM"}


def knee_rotations(side: str) -> tuple[str, str, str]:
    """Names of the knee rotations of `side` (flexion, adduction, rotation; rad)."""
    return (f"knee_flexion_{side}", f"knee_adduction_{side}", f"knee_rotation_{side}")


def knee_translations(side: str) -> tuple[str, str, str]:
    """Names of the knee translations of `side` (anterior, proximal, lateral in the femur frame; m)."""
    return (f"knee_tx_{side}", f"knee_ty_{side}", f"knee_tz_{side}")


def knee_coordinates(side: str) -> tuple[str, ...]:
    return knee_rotations(side) + knee_translations(side)


def _constant_rows(coordinates: Sequence[str], values: Mapping[str, float]) -> LinearCoupling | None:
    """Rows ``q_i = v_i`` (a held coordinate is a coupling with no independent)."""
    out = None
    for name, v in values.items():
        row = LinearCoupling.correlative(coordinates, name, {}, float(v))
        out = row if out is None else out.stack(row)
    return out


# --------------------------------------------------------------------------- knee models
@dataclass(frozen=True)
class HingeKnee:
    """1-DOF knee: flexion free, the other five coordinates held at `fixed` (rad / m)."""

    side: str
    fixed: tuple[tuple[str, float], ...]
    label: str = "1DOF"

    @property
    def n_dof(self) -> int:
        return 1

    def constraints(self, coordinates: Sequence[str]):
        """(LinearCoupling rows, couplers) over `coordinates`."""
        return _constant_rows(coordinates, dict(self.fixed)), ()


@dataclass(frozen=True, eq=False)
class PlanarSplineKnee:
    """3-DOF planar knee (gait2392 style): ``tx = Sx(a1)``, ``ty = Sy(a1)``, the rest held.

    Attributes
    ----------
    knots : (K,) flexion knots, rad (strictly increasing)
    tx, ty : (K,) translations at the knots, m (natural cubic splines, linear outside)
    fixed : ((name, value), ...) adduction, rotation and tz held (rad, m)
    """

    side: str
    knots: np.ndarray
    tx: np.ndarray
    ty: np.ndarray
    fixed: tuple[tuple[str, float], ...]
    label: str = "3DOF"

    def __post_init__(self):
        for n in ("knots", "tx", "ty"):
            a = np.array(getattr(self, n), dtype=float)
            a.setflags(write=False)
            object.__setattr__(self, n, a)

    @property
    def n_dof(self) -> int:
        return 1

    def splines(self) -> tuple[NaturalCubicSpline, NaturalCubicSpline]:
        return NaturalCubicSpline(self.knots, self.tx), NaturalCubicSpline(self.knots, self.ty)

    def translations(self, flexion) -> np.ndarray:
        """(F, 2) tx, ty at flexion (F,) rad."""
        sx, sy = self.splines()
        return np.column_stack([sx(np.asarray(flexion, float)), sy(np.asarray(flexion, float))])

    def constraints(self, coordinates: Sequence[str]):
        flex = knee_rotations(self.side)[0]
        tx, ty, _ = knee_translations(self.side)
        sx, sy = self.splines()
        couplers = (CoordinateCoupler(tx, (flex,), sx, f"{tx}_spline"),
                    CoordinateCoupler(ty, (flex,), sy, f"{ty}_spline"))
        return _constant_rows(coordinates, dict(self.fixed)), couplers


@dataclass(frozen=True, eq=False)
class CorrelativeKnee:
    """3+DOF correlative knee: rotations free, translations the linear law (seed eq. 1/2)."""

    side: str
    law: CorrelativeLaw
    label: str = "3+DOF"

    @property
    def n_dof(self) -> int:
        return len(self.law.independent)

    def constraints(self, coordinates: Sequence[str]):
        return self.law.to_coupling(coordinates), ()


@dataclass(frozen=True)
class FreeKnee:
    """6-DOF knee (no constraint): the lower bound of the tracking error any knee model can reach."""

    side: str
    label: str = "6DOF"

    @property
    def n_dof(self) -> int:
        return 6

    def constraints(self, coordinates: Sequence[str]):
        return None, ()


def strip_knee_constraints(model: Model, sides: Iterable[str]) -> Model:
    """`model` without the coupling rows and couplers that involve the knee coordinates of `sides`."""
    names = set()
    for s in sides:
        names.update(knee_coordinates(s))
    couplings = None if model.couplings is None else model.couplings.without(names)
    couplers = tuple(cp for cp in model.couplers if not ({cp.dependent, *cp.independent} & names))
    return model.replace(couplings=couplings, couplers=couplers)


def free_knee_model(model: Model, sides: Iterable[str] = ("r", "l")) -> Model:
    """The six-DOF (unconstrained) knee of the seed's data collection (section 3.2)."""
    sides = tuple(sides)
    missing = [c for s in sides for c in knee_coordinates(s) if c not in model.coordinate_names]
    if missing:
        raise InputError(model.name, f"model has no knee coordinate {', '.join(missing)} "
                                     "(a six-coordinate knee: knee_flexion/adduction/rotation_<side>, knee_tx/ty/tz_<side>)")
    return strip_knee_constraints(model, sides)


def with_knees(model: Model, knees: Sequence) -> Model:
    """`model` with the knee constraints replaced by `knees` (one knee model per side)."""
    sides = [k.side for k in knees]
    if len(set(sides)) != len(sides):
        raise InputError(model.name, f"two knee models for one side ({sides})")
    base = free_knee_model(model, sides)
    names = base.coordinate_names
    rows = base.couplings
    couplers = list(base.couplers)
    for k in knees:
        r, c = k.constraints(names)
        if r is not None:
            rows = r.over(names) if rows is None else rows.stack(r.over(names)).over(names)
        couplers.extend(c)
    return base.replace(couplings=rows, couplers=tuple(couplers))


# --------------------------------------------------------------------------- training data
@dataclass(frozen=True, eq=False)
class KneeKinematics:
    """Per-frame knee coordinates from IK with a free knee (the seed's regression data).

    rotations : (F, 3) rad (flexion, adduction, rotation); translations : (F, 3) m;
    groups : (F,) trial label per frame; side : str
    """

    side: str
    rotations: np.ndarray
    translations: np.ndarray
    groups: np.ndarray

    @property
    def n_frames(self) -> int:
        return self.rotations.shape[0]


def knee_kinematics(results: Sequence[IKResult], side: str, labels: Sequence[str] | None = None) -> KneeKinematics:
    """Knee coordinates of `side` from free-knee IK results, frames the markers determined only."""
    rot, tr, grp = [], [], []
    for i, res in enumerate(results):
        ix = [res.coordinates.index(c) for c in knee_coordinates(side)]
        ok = res.solved & np.isfinite(res.q).all(axis=1)
        if res.determined is not None:
            ok &= res.determined
        q = res.q[ok][:, ix]
        rot.append(q[:, :3])
        tr.append(q[:, 3:])
        grp.append(np.full(q.shape[0], labels[i] if labels is not None else f"trial{i}", dtype=object))
    if not rot or sum(len(r) for r in rot) == 0:
        raise InputError(None, "no determined IK frame to learn the knee from")
    return KneeKinematics(side, np.vstack(rot), np.vstack(tr), np.concatenate(grp))


def fit_hinge_knee(kin: KneeKinematics, planar: "PlanarSplineKnee | None" = None,
                   default_flexion: float = 0.0) -> HingeKnee:
    """1-DOF knee from the training frames.

    With `planar` (the seed's 1DOF, section 4.1): the same axis as the planar
    knee (its held adduction, rotation and tz) and its knee centre at the
    default pose, ``tx, ty = Sx(a1_0), Sy(a1_0)`` with ``a1_0 = default_flexion``.
    Without: the least-squares constants of the training frames (their means,
    minimising ``sum_f |q_c(f) - v_c|^2`` per held coordinate), the best
    constant knee the same data allow (a stronger baseline than the seed's).
    """
    rn, tn = knee_rotations(kin.side), knee_translations(kin.side)
    if planar is not None:
        if planar.side != kin.side:
            raise InputError(None, f"planar knee of side {planar.side!r} for a hinge of side {kin.side!r}")
        tx, ty = planar.translations(np.array([float(default_flexion)]))[0]
        vals = list(planar.fixed) + [(tn[0], tx), (tn[1], ty)]
        return HingeKnee(kin.side, tuple((n, float(v)) for n, v in vals))
    vals = [(rn[1], kin.rotations[:, 1].mean()), (rn[2], kin.rotations[:, 2].mean())]
    vals += [(n, kin.translations[:, k].mean()) for k, n in enumerate(tn)]
    return HingeKnee(kin.side, tuple((n, float(v)) for n, v in vals))


def fit_spline_basis(knots: np.ndarray, x: np.ndarray) -> np.ndarray:
    """(F, K) values at x of the natural cubic splines through unit knot values (the spline is linear in y)."""
    K = len(knots)
    return np.column_stack([NaturalCubicSpline(knots, np.eye(K)[k])(x) for k in range(K)])


def fit_planar_spline_knee(kin: KneeKinematics, n_knots: int = 6) -> PlanarSplineKnee:
    """Least-squares natural cubic splines ``tx(a1)``, ``ty(a1)`` on equally spaced flexion knots.

    Model: ``t_d(f) = sum_k y_dk B_k(a1(f))`` with ``B_k`` the natural spline through
    unit knot values; minimised ``sum_f (t_d(f) - sum_k y_dk B_k(a1(f)))^2`` per
    direction d.  Knots span the training flexion range; the held adduction,
    rotation and tz are their training means.
    """
    a1 = kin.rotations[:, 0]
    lo, hi = float(np.min(a1)), float(np.max(a1))
    if not hi - lo > 1e-3:
        raise FitError(f"knee {kin.side}: flexion does not vary in the training frames ({lo:.4f}..{hi:.4f} rad)")
    K = max(2, min(int(n_knots), kin.n_frames // 4))
    knots = np.linspace(lo, hi, K)
    B = fit_spline_basis(knots, a1)
    Y, *_ = np.linalg.lstsq(B, kin.translations[:, :2], rcond=None)
    rn, tn = knee_rotations(kin.side), knee_translations(kin.side)
    fixed = ((rn[1], float(kin.rotations[:, 1].mean())), (rn[2], float(kin.rotations[:, 2].mean())),
             (tn[2], float(kin.translations[:, 2].mean())))
    return PlanarSplineKnee(kin.side, knots, Y[:, 0], Y[:, 1], fixed)


def fit_correlative_knee(kin: KneeKinematics, joint: str | None = None) -> CorrelativeKnee:
    """Seed eq. (1) by multiple linear regression on the free-knee frames (`kinematics.mechanisms.correlative_fit.fit_law`)."""
    law = fit_law(kin.rotations, kin.translations, knee_rotations(kin.side), knee_translations(kin.side),
                  groups=kin.groups, joint=joint or f"knee_{kin.side}", source=f"knee_{kin.side} training frames")
    return CorrelativeKnee(kin.side, law)


# --------------------------------------------------------------------------- scoring
@dataclass(frozen=True)
class TrialScore:
    """IK tracking error of one trial with one knee model.

    total : sum over frames of the frame RMS over the scored markers, m (the seed's Table 3 value)
    mean_rms : mean frame RMS, m
    frames : frames scored
    """

    trial: str
    model: str
    total: float
    mean_rms: float
    frames: int

    def to_dict(self) -> dict:
        return {"trial": self.trial, "model": self.model, "sum_rms_m": self.total, "mean_rms_m": self.mean_rms,
                "frames": self.frames}


def score_trial(result: IKResult, scored: Sequence[str], trial: str = "", model: str = "") -> TrialScore:
    """Seed 4.1 score: ``sum_f sqrt(mean_m |x_m(q_f) - y_m,f|^2)`` over the `scored` markers present."""
    cols = [result.markers.index(m) for m in scored if m in result.markers]
    if not cols:
        raise InputError(trial or None, f"none of the scored markers {list(scored)} was tracked")
    e = result.marker_errors[:, cols]
    present = np.isfinite(e)
    n = present.sum(axis=1)
    ok = n > 0
    rms = np.sqrt(np.where(present, e**2, 0.0).sum(axis=1)[ok] / n[ok])
    return TrialScore(trial, model, float(rms.sum()), float(rms.mean()), int(ok.sum()))


def track(model: Model, trials: Sequence[MarkerTrial], tracked: Sequence[str], **ik) -> list[IKResult]:
    """Marker IK of each trial with equal weights on the `tracked` markers present (the seed's IK tool setting)."""
    out = []
    for tr in trials:
        w = {m: 1.0 for m in tracked if m in tr.names}
        out.append(solve_ik(model, tr, marker_weights=w, **ik))
    return out


def knee_coordinate_errors(result: IKResult, q_true, true_coordinates: Sequence[str], side: str) -> np.ndarray:
    """RMS over the solved frames of the IK knee coordinates minus the true ones.

    ``e_c = sqrt(mean_f (q_c(f) - q*_c(f))^2)`` for the six knee coordinates of
    `side` (`knee_coordinates`: three rotations in rad, three translations in m),
    `q_true` (F, len(true_coordinates)) being the known coordinates of the
    trial's frames (a phantom's truth).  Tracking error says how well markers
    are fitted; this says whether the knee the fit implies is the true one
    (a law can also absorb soft-tissue artefact).
    """
    q_true = np.asarray(q_true, float)
    names = knee_coordinates(side)
    if q_true.shape[0] != result.q.shape[0]:
        raise InputError(None, f"{q_true.shape[0]} true frames for {result.q.shape[0]} IK frames")
    true_names = list(true_coordinates)
    missing = [c for c in names if c not in true_names or c not in result.coordinates]
    if missing:
        raise InputError(None, f"knee coordinates {', '.join(missing)} missing from the IK result or the truth")
    ok = result.solved & np.isfinite(result.q).all(axis=1)
    d = result.q[ok][:, [result.coordinates.index(c) for c in names]] - q_true[ok][:, [true_names.index(c) for c in names]]
    return np.sqrt(np.mean(d**2, axis=0))


def summarize(scores: Sequence[TrialScore]) -> dict:
    """Mean (and sd) over trials of the total and mean frame RMS."""
    t = np.array([s.total for s in scores])
    r = np.array([s.mean_rms for s in scores])
    return {"trials": len(scores), "sum_rms_m_mean": float(t.mean()), "sum_rms_m_sd": float(t.std(ddof=1)) if len(t) > 1 else 0.0,
            "mean_rms_m": float(r.mean()), "frames": int(sum(s.frames for s in scores))}


def reduction(better: Sequence[TrialScore], worse: Sequence[TrialScore]) -> tuple[float, float]:
    """Per-trial error reduction ``1 - e_better / e_worse`` (percent): mean and sd over trials (seed 4.1)."""
    if [s.trial for s in better] != [s.trial for s in worse]:
        raise InputError(None, "reductions need the same trials for both models")
    r = 100.0 * (1.0 - np.array([b.total for b in better]) / np.array([w.total for w in worse]))
    return float(r.mean()), float(r.std(ddof=1)) if r.size > 1 else 0.0


def _cell(scores: Sequence[TrialScore], digits: int) -> str:
    s = summarize(scores)
    return f"{s['sum_rms_m_mean']:.{digits}f} ({1e3 * s['mean_rms_m']:.2f} mm)"


def tracking_table(scores: Mapping[str, Mapping[str, Sequence[TrialScore]]], columns: Sequence[str],
                   title: str, corner: str = "Subject1", digits: int = 2) -> TextTable:
    """Seed Table 3/4/5 form: rows motions, columns knee models.

    Cells: mean over trials of the summed frame RMS (m), with the mean frame RMS in mm.

    Parameters
    ----------
    scores : ``{row (motion): {column (model): [TrialScore, ...]}}``
    """
    rows = []
    for motion, by_model in scores.items():
        rows.append((motion,) + tuple(_cell(by_model[c], digits) if c in by_model else "" for c in columns))
    return TextTable((corner,) + tuple(columns), tuple(rows), title)


# --------------------------------------------------------------------------- protocol
@dataclass(frozen=True, eq=False)
class TrainedKnees:
    """Knee models learnt from one training set (one per side each).

    kinematics : side -> KneeKinematics (free-knee IK frames)
    models : label (``1DOF``, ``1DOF-LS``, ``3DOF``, ``3+DOF``) -> tuple of knee models, one per side
    training_rms : mean marker RMS of the free-knee IK on the training trials, m
    """

    kinematics: dict
    models: dict
    training_rms: float

    @property
    def laws(self) -> dict:
        """side -> CorrelativeLaw."""
        return {k.side: k.law for k in self.models["3+DOF"]}


def train_knees(model: Model, trials: Sequence[MarkerTrial], tracked: Sequence[str], sides: Sequence[str] = ("r", "l"),
                n_knots: int = 6, default_flexion: float = 0.0, **ik) -> TrainedKnees:
    """Seed 3.2: free six-DOF knee IK on `trials`, then every knee model fitted on its frames.

    Returns hinge (seed form, `1DOF`, and least-squares, `1DOF-LS`), planar spline
    (`3DOF`) and correlative (`3+DOF`) knees for each side.
    """
    free = free_knee_model(model, sides)
    res = track(free, trials, tracked, **ik)
    labels = [t.source or f"trial{i}" for i, t in enumerate(trials)]
    kins = {s: knee_kinematics(res, s, labels) for s in sides}
    rms = float(np.nanmean(np.concatenate([r.rms for r in res])))
    return TrainedKnees(kins, fit_knee_models(kins, n_knots, default_flexion), rms)


def fit_knee_models(kinematics: Mapping[str, KneeKinematics], n_knots: int = 6,
                    default_flexion: float = 0.0) -> dict:
    """Every knee model fitted on free-knee frames: ``{label: (model per side, ...)}``.

    Labels ``1DOF`` (seed hinge), ``1DOF-LS``, ``3DOF`` (planar splines) and ``3+DOF``
    (correlative law), in the order of `kinematics` (side -> KneeKinematics).
    """
    models = {"1DOF": [], "1DOF-LS": [], "3DOF": [], "3+DOF": []}
    for kin in kinematics.values():
        planar = fit_planar_spline_knee(kin, n_knots)
        models["3DOF"].append(planar)
        models["1DOF"].append(fit_hinge_knee(kin, planar, default_flexion))
        models["1DOF-LS"].append(replace(fit_hinge_knee(kin), label="1DOF-LS"))
        models["3+DOF"].append(fit_correlative_knee(kin))
    return {k: tuple(v) for k, v in models.items()}


def select_frames(kin: KneeKinematics, keep: np.ndarray) -> KneeKinematics:
    """The frames of `kin` where the boolean mask `keep` (F,) is true."""
    keep = np.asarray(keep, bool)
    if keep.shape != (kin.n_frames,):
        raise InputError(None, f"frame mask of shape {keep.shape} for {kin.n_frames} frames")
    if not keep.any():
        raise InputError(None, f"knee {kin.side}: no training frame selected")
    return KneeKinematics(kin.side, kin.rotations[keep], kin.translations[keep], kin.groups[keep])


def sub_motion_knees(trained: TrainedKnees, sub_motion: Callable[[str], str], n_knots: int = 6,
                     default_flexion: float = 0.0) -> dict:
    """Seed 3.3: knee models per sub-motion (e.g. crouch per foot angle).

    The training frames are grouped by ``sub_motion(trial label)`` and every
    knee model (`fit_knee_models`) is fitted on each group alone.

    Returns
    -------
    ``{sub-motion: {label: (model per side, ...)}}`` in order of first appearance.
    """
    kins = trained.kinematics
    first = next(iter(kins.values()))
    keys = np.array([sub_motion(str(g)) for g in first.groups], dtype=object)
    out = {}
    for key in dict.fromkeys(keys.tolist()):
        sel = {s: select_frames(k, np.array([sub_motion(str(g)) == key for g in k.groups]))
               for s, k in kins.items()}
        out[key] = fit_knee_models(sel, n_knots, default_flexion)
    return out


def compare_knees_by_sub_motion(model: Model, knees_by_sub: Mapping[str, Mapping[str, Sequence]],
                                trials: Sequence[MarkerTrial], sub_motion: Callable[[str], str],
                                tracked: Sequence[str], labels: Sequence[str] = ("1DOF", "3DOF", "3+DOF"),
                                suffix: str = " sub", **ik) -> dict:
    """IK of each trial with the knee models of its own sub-motion (seed 3.3 sub-motion laws).

    Returns ``{label + suffix: [IKResult per trial]}`` in the order of `trials`.
    """
    out = {lab + suffix: [None] * len(trials) for lab in labels}
    for i, tr in enumerate(trials):
        key = sub_motion(tr.source or f"trial{i}")
        if key not in knees_by_sub:
            raise InputError(tr.source, f"no knee model for sub-motion {key!r} (have {sorted(knees_by_sub)})")
        for lab in labels:
            out[lab + suffix][i] = track(with_knees(model, knees_by_sub[key][lab]), [tr], tracked, **ik)[0]
    return out


def compare_knees(model: Model, knees: Mapping[str, Sequence], trials: Sequence[MarkerTrial], tracked: Sequence[str],
                  progress: Callable[[str], None] | None = None, **ik) -> dict:
    """IK of `trials` with each knee model set: ``{label: [IKResult per trial]}`` (score with `score_results`)."""
    out = {}
    for label, ks in knees.items():
        out[label] = track(with_knees(model, ks), trials, tracked, **ik)
        if progress is not None:
            progress(label)
    return out


def score_results(results: Mapping[str, Sequence[IKResult]], trials: Sequence[MarkerTrial],
                  scored: Sequence[str]) -> dict:
    """``{label: [TrialScore per trial]}`` of `compare_knees` results over the `scored` markers."""
    return {label: [score_trial(r, scored, t.source or f"trial{i}", label) for i, (r, t) in enumerate(zip(res, trials))]
            for label, res in results.items()}



# --------------------------------------------------------------------------- IK protocols
def undetermined_coordinates(model: Model, markers: Sequence[str], q=None, tol: float = 1e-8) -> tuple[str, ...]:
    """Coordinates that `markers` do not determine at pose `q` (default: the default pose).

    With ``J = (dx_m/dq) (dq/dz)`` the (3M, n_z) Jacobian of the markers with
    respect to the free parameters z of `kinematics.algorithms.coordinate_map.coordinate_map`, the
    directions ``dz`` with ``|J dz| <= tol sigma_max |dz|`` move no marker;
    the coordinates those directions move (``|dq| > 1e-6``) are returned
    (empty: IK on `markers` is determined, as `IKResult.determined` checks per frame).
    """
    cmap = coordinate_map(model)
    if cmap.n_z == 0:
        return ()
    q = model.default_q if q is None else np.asarray(q, float)
    q = cmap.expand(cmap.project(q))[0]
    _, Jq = marker_jacobian(model, q, list(markers))
    E = cmap.jacobian(q)[0]
    J = Jq.reshape(-1, model.n_q) @ E
    _, sv, Vt = np.linalg.svd(J, full_matrices=True)
    sv = np.concatenate([sv, np.zeros(max(0, cmap.n_z - sv.size))])
    null = Vt[sv <= tol * max(sv[0], 1e-300)]
    if null.size == 0:
        return ()
    moved = np.abs(E @ null.T).max(axis=1) > 1e-6
    return tuple(n for n, m in zip(model.coordinate_names, moved) if m)


def leg_model(model: Model, markers: Sequence[str], lock_root_rotations: bool = True) -> Model:
    """The part of `model` that `markers` observe: the seed's IK model of one leg (section 3.2).

    Kept: the bodies carrying one of `markers` and their ancestors (seven leg
    markers: pelvis, thigh, shank); removed: every other body (the other leg,
    the foot distal to the malleoli), its joints and coordinates, the other
    markers and frames, and the coupling rows, inequalities and couplers that
    involve a removed coordinate.  With `lock_root_rotations`, when the root
    body (the pelvis) carries none of `markers`, the rotations of its joint
    are locked at their default: the root's translations and the next joint's
    rotations (the hip) then are the six free coordinates of the thigh, which
    the markers determine; unlocked, the pelvis orientation and the hip angles
    would trade off freely (three undetermined directions).

    Raises
    ------
    InputError
        A marker the model lacks, or markers that leave coordinates of the kept
        model undetermined (named) at the default pose.
    """
    markers = tuple(dict.fromkeys(markers))
    missing = [m for m in markers if m not in model.marker_names]
    if missing:
        raise InputError(model.name, f"no marker {', '.join(missing)} in the model")
    if not markers:
        raise InputError(model.name, "a leg model needs markers")
    keep = {GROUND}
    for m in markers:
        b = model.body_index(model.marker(m).body)
        while b >= 0:
            keep.add(model.bodies[b].name)
            b = model.parent[b]
    joints = tuple(j for j in model.joints if j.child in keep)
    read = {c for j in joints for c in j.coordinates}
    dropped = {c for j in model.joints if j.child not in keep for c in j.coordinates} - read
    coords = [c for c in model.coordinates if c.name not in dropped]
    names = tuple(c.name for c in coords)
    if lock_root_rotations:
        root = next(j for j in joints if j.parent == GROUND)
        if not any(model.marker(m).body == root.child for m in markers):
            rot = {c.name for c in coords if c.name in root.coordinates and c.kind == "rotational"}
            coords = [replace(c, locked=True) if c.name in rot else c for c in coords]
    couplings = None if model.couplings is None else model.couplings.without(dropped)
    if couplings is not None:
        couplings = couplings.over(names)
    ineq = model.inequalities
    if ineq is not None:
        cols = [i for i, c in enumerate(ineq.coordinates) if c in dropped]
        ok = ~np.any(ineq.matrix[:, cols] != 0, axis=1) if cols else np.ones(ineq.matrix.shape[0], bool)
        ineq = None if not ok.any() else LinearInequalities(
            ineq.coordinates, ineq.matrix[ok], ineq.rhs[ok], tuple(l for l, k in zip(ineq.labels, ok) if k)).over(names)
    couplers = tuple(cp for cp in model.couplers if not ({cp.dependent, *cp.independent} & dropped))
    out = model.replace(bodies=tuple(b for b in model.bodies if b.name in keep), joints=joints, coordinates=tuple(coords),
                        markers=tuple(model.marker(m) for m in markers),
                        frames=tuple(f for f in model.frames if f.body in keep), couplings=couplings,
                        inequalities=ineq, couplers=couplers, name=f"{model.name} ({len(markers)}-marker leg)")
    bad = undetermined_coordinates(out, markers)
    if bad:
        raise InputError(model.name, f"markers {', '.join(markers)} do not determine {', '.join(bad)} "
                                     "(lock them or add markers)")
    return out


@dataclass(frozen=True)
class TrackingProtocol:
    """How the experiments run IK: markers tracked (equal weights), knees learnt, model used.

    name : str
    tracked : markers tracked (and scored by default)
    sides : knees learnt and compared (``("r",)`` or ``("r", "l")``)
    one_leg : IK on `leg_model` (the bodies the tracked markers observe) instead of the whole model
    """

    name: str
    tracked: tuple[str, ...]
    sides: tuple[str, ...]
    one_leg: bool = False

    def model(self, model: Model) -> Model:
        """The IK model of this protocol built from the subject's `model`."""
        return leg_model(model, self.tracked) if self.one_leg else model


def seed_protocol(markers: Sequence[str] = tuple(SEED_MARKERS.values()), side: str = "r") -> TrackingProtocol:
    """The seed's protocol (section 3.2): IK driven by seven markers of one leg only, equal weights, one knee."""
    return TrackingProtocol("seed7", tuple(markers), (side,), one_leg=True)


def whole_body_protocol(tracked: Sequence[str], sides: Sequence[str] = ("r", "l")) -> TrackingProtocol:
    """IK of the whole model on every marker of `tracked` (pelvis and both legs), both knees learnt."""
    return TrackingProtocol("whole-body", tuple(tracked), tuple(sides), one_leg=False)
