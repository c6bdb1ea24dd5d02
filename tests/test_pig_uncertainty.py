"""Plug-in-Gait's propagated covariance (`personalize.pipeline.pig_uncertainty`) against Monte Carlo on a real static."""
import numpy as np

from kinematics.gait.reconstruction import reconstruct
from kinematics.gait.subject import read_vsk
from kinematics.io.c3d import read_c3d
from kinematics.io.markers import MarkerTrial
from personalize.pipeline import pig_uncertainty as pu


def test_linearised_covariance_matches_monte_carlo_on_the_nexus_static(shared_data):
    """Vicon's own Plug-in-Gait static (mocap_pig): 400 draws of the markers' placement errors through the
    reconstruction give the centres' and axes' covariances the forward-difference Jacobian predicts."""
    d = shared_data / "mocap_pig"
    static = read_c3d(d / "Static_trial.c3d")
    subject = read_vsk(d / "Test.vsk")
    u = pu.pig_uncertainty(static, subject)
    med = np.nanmedian(static.positions, axis=0)
    sd = np.array([pu._marker_sd(n) or 0.0 for n in static.names])
    rng = np.random.default_rng(3)
    n = 400
    frames = med[None] + rng.normal(size=(n,) + med.shape) * sd[None, :, None]
    base = MarkerTrial(static.names, np.repeat(med[None], 3, axis=0), static.rate, np.arange(3) / static.rate)
    mc = reconstruct(MarkerTrial(static.names, frames, static.rate, np.arange(n) / static.rate), "pig", static=base,
                     subject=subject, check_static=False)
    for joint in ("knee_r", "knee_l", "ankle_r", "ankle_l"):
        pred = np.sqrt(np.trace(u.centres[joint]))
        got = np.sqrt(np.trace(np.cov(mc.centres[joint].T)))
        assert 5e-3 < pred < 0.06, (joint, pred)          # mm-to-cm: the placement sds of 8-10 mm, amplified
        assert abs(got / pred - 1) < 0.15, (joint, got, pred)
    for seg in ("femur_r", "tibia_torsioned_r"):
        pred = np.sqrt(np.trace(u.axes[seg]))
        got = np.sqrt(np.trace(np.cov(np.asarray(mc.segments[seg].axes)[:, :, 1].T)))
        assert abs(got / pred - 1) < 0.2, (seg, got, pred)

