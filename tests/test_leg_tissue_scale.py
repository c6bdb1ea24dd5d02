"""The soft tissue under a leg segment's bony markers: the site prior times the subject's scale k estimated
with the pelvis (personalize.pipeline.segment_registration, model_checks.prior_tissue)."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from kinematics.io.marker_sets import MarkerDef, MarkerSet
from lowerlimb.estimates import Gaussian
from lowerlimb.geometry import DEFAULT_MARKER_RADIUS
from personalize.landmarks import BoneLandmarks, Landmark
from personalize.pipeline.model_checks import prior_tissue
from personalize.pipeline.segment_registration import register_with_centre
from personalize.registration import skin_prior


def _segment(k: float):
    """A spherical 'femur' (radius 40 mm) with three bony landmarks on it and the hip centre above it; the markers
    of a subject of tissue scale k, in a lab turned and shifted from the scanner."""
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=0.04)
    dirs = {"RTRO": [1.0, 0.2, 0.0], "RKNE": [0.0, 0.3, 1.0], "RMFC": [0.0, 0.3, -1.0]}
    lm = {n: 0.04 * np.asarray(d) / np.linalg.norm(d) for n, d in dirs.items()}
    cov = 1e-8 * np.eye(3)
    bone = BoneLandmarks(bone="femur_r", side="r", landmarks={n: Landmark(p, cov) for n, p in lm.items()})
    R, t = Rotation.from_rotvec([0.2, -0.4, 0.3]).as_matrix(), np.array([0.5, -0.2, 0.9])
    static = {}
    for n, p in lm.items():
        off = k * skin_prior(n)[0] + DEFAULT_MARKER_RADIUS
        static[n] = Gaussian(R @ (p * (1.0 + off / 0.04)) + t, 0.005 ** 2 * np.eye(3))   # palpation-like sd
    centre = np.array([0.0, 0.35, 0.0])                  # the hip centre, far above the condyles
    return bone, mesh, static, centre, R, t


@pytest.mark.parametrize("k", [0.4, 2.0])
def test_the_pelvis_tissue_scale_carries_to_the_leg(k):
    bone, mesh, static, c, R, t = _segment(k)
    args = ("femur_r", {"femur_r": bone}, ["femur_r"], ("RKNE", "RMFC", "RTRO"), static, {"femur_r": mesh},
            Gaussian(c, 1e-8 * np.eye(3)), Gaussian(R @ c + t, 0.01 ** 2 * np.eye(3)))
    scaled = register_with_centre(*args, tissue_scale=(k, 0.05))
    prior = register_with_centre(*args)
    err = lambda reg: np.linalg.norm(reg.transfer_point(c)[0] - (R @ c + t))      # noqa: E731
    p = R @ bone.landmarks["RTRO"].position + t
    err_tro = lambda reg: np.linalg.norm(reg.transfer_point(bone.landmarks["RTRO"].position)[0] - p)  # noqa: E731
    assert err_tro(scaled) < 0.5e-3 and err(scaled) < 0.5e-3
    # the adult prior alone misplaces the bone: |k - 1| x 31 mm of tissue at the trochanter
    assert err_tro(prior) > 1e-3 and err(prior) > 5.0 * err(scaled)


def test_prior_tissue_raises_the_marker_limit_of_a_thick_subject():
    est = SimpleNamespace(registrations={"pelvis": SimpleNamespace(tissue_scale=2.0, tissue_scale_log_sd=0.2)})
    ms = MarkerSet("lab", {"GT_R": MarkerDef("femur_r", "RTRO"), "TH_R": MarkerDef("femur_r")})
    got = prior_tissue(est, ms, ["GT_R", "TH_R"])
    assert set(got) == {"GT_R"}                                           # wands and clusters have no site prior
    t0, sd0 = skin_prior("RTRO")
    assert got["GT_R"].thickness == pytest.approx(2.0 * t0)
    assert got["GT_R"].sd == pytest.approx(np.hypot(2.0 * sd0, 2.0 * t0 * 0.2))
    assert 2.0 * t0 + 3.0 * got["GT_R"].sd > 0.06                         # 62 mm of tissue + 3 sd passes
    assert prior_tissue(SimpleNamespace(registrations={"pelvis": SimpleNamespace(tissue_scale=None)}), ms, ["GT_R"]) == {}
