"""OpenSim export of correlative joints (kinematics.mechanisms.correlative_export), verified in OpenSim 4.6."""
from __future__ import annotations

import numpy as np
import pytest

from correlative_experiments import free_knee_model
from kinematics.mechanisms.correlative_export import (
    add_to_osim, correlative_function, export_correlative_model, polynomial_layout, verify_osim_law,
)
from lowerlimb.errors import InputError
from kinematics.algorithms.fk import marker_positions
from kinematics.io.opensim_io import save_osim
from phantoms import make_phantom
from phantoms.skeleton import phantom_skeleton


@pytest.fixture(scope="module")
def skeleton():
    return phantom_skeleton(make_phantom(0))


@pytest.fixture(scope="module")
def exported(skeleton, tmp_path_factory, opensim):
    laws = [skeleton.knee_laws["r"], skeleton.knee_laws["l"]]
    path = export_correlative_model(skeleton.model, laws, tmp_path_factory.mktemp("osim") / "knee.osim")
    return path, laws


def test_opensim_function_equals_the_law(opensim):
    assert sorted(polynomial_layout(3)) == [0, 1, 2]
    c, c0 = np.array([0.0023, -0.0006, 0.0008]), 1e-4
    f = correlative_function(c, c0)
    for x in np.random.default_rng(1).uniform(-1, 1, (4, 3)):
        v = opensim.Vector(3, 0.0)
        for i in range(3):
            v.set(i, float(x[i]))
        assert f.calcValue(v) == pytest.approx(c0 + c @ x, abs=1e-15)


def test_assembled_opensim_pose_satisfies_the_law(exported):
    path, laws = exported
    chk = verify_osim_law(path, laws, n_poses=6)
    assert set(chk.constraints) == {f"correlative_knee_t{a}_{s}" for a in "xyz" for s in "rl"}
    assert chk.max_law_error < 1e-8                    # m
    assert chk.max_independent_shift < 1e-6            # rad: assembly moved the translations, not the rotations
    assert chk.max_dependent_correction > 4e-3         # the dependents started 5 mm off: assembly did the work


def test_opensim_and_engine_agree_on_marker_positions(exported, skeleton, opensim):
    """FK honours the law in both: OpenSim's assembled pose gives the engine's markers."""
    path, laws = exported
    om = opensim.Model(str(path))
    s = om.initSystem()
    cs, ms = om.getCoordinateSet(), om.getMarkerSet()
    model = skeleton.model
    rng = np.random.default_rng(3)
    for _ in range(3):
        q = skeleton.standing_q.copy()
        for law in laws:
            for n in law.independent:
                i = model.coordinate_index(n)
                q[i] += rng.uniform(-0.3, 0.3) if "flexion" not in n else rng.uniform(0.2, 1.2)
        for c in model.coordinates:
            cs.get(c.name).setValue(s, float(q[model.coordinate_index(c.name)]), False)
        om.assemble(s)
        qa = np.array([cs.get(c.name).getValue(s) for c in model.coordinates])
        om.realizePosition(s)
        names = ["RKNE", "RTIB", "RANK", "RHEE", "LANK", "LTOE"]
        x_os = np.array([[ms.get(n).getLocationInGround(s).get(k) for k in range(3)] for n in names])
        x_en = marker_positions(model, qa, names)
        np.testing.assert_allclose(x_os, x_en, atol=1e-9)
        # and the engine's own law gives the same translations
        np.testing.assert_allclose(qa, skeleton.complete(qa[None])[0], atol=1e-9)


def test_constraints_added_to_an_existing_osim(skeleton, tmp_path, opensim):
    """Post-processing a user's .osim (here the free-knee phantom) adds the law; a wrong law is detected."""
    free = tmp_path / "free.osim"
    save_osim(free_knee_model(skeleton.model), free)
    law = skeleton.knee_laws["r"]
    out = add_to_osim(free, [law], tmp_path / "with_law.osim")
    assert verify_osim_law(out, [law], n_poses=4).max_law_error < 1e-8
    other = law.scaled(1.5)
    assert verify_osim_law(out, [other], n_poses=4).max_law_error > 1e-4
    # the law on the left knee too, replacing nothing else
    out2 = add_to_osim(out, [law, skeleton.knee_laws["l"]], tmp_path / "both.osim")
    chk = verify_osim_law(out2, [law, skeleton.knee_laws["l"]], n_poses=3)
    assert chk.max_law_error < 1e-8 and len(chk.constraints) == 6


def test_bad_exports_write_nothing(skeleton, tmp_path, opensim):
    law = skeleton.knee_laws["r"]
    bad = type(law)(joint="x", independent=("knee_flexion_r", "nope_r"), dependent=("knee_tx_r",),
                    coefficients=[[0.001, 0.002, 0.0]])
    target = tmp_path / "bad.osim"
    with pytest.raises(InputError, match="nope_r"):
        export_correlative_model(skeleton.model, [bad], target)
    assert not target.exists()
    with pytest.raises(InputError, match="dependent of two laws"):
        export_correlative_model(skeleton.model, [law, law], target)
    assert not target.exists() and not list(tmp_path.iterdir())
    (tmp_path / "junk.osim").write_text("not xml")
    with pytest.raises(InputError):
        add_to_osim(tmp_path / "junk.osim", [law], tmp_path / "out.osim")
    assert not (tmp_path / "out.osim").exists()
