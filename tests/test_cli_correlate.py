"""``personalize correlate``: law.json, tables and plot from .mot/.sto kinematics."""
from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from kinematics.mechanisms.correlative import CorrelativeLaw
from kinematics.mechanisms.correlative_fit import fit_law
from kinematics.io.storage import read_sto, write_mot
from personalize.cli import main

IND = ["knee_flexion_r", "knee_adduction_r", "knee_rotation_r"]
DEP = ["knee_tx_r", "knee_ty_r", "knee_tz_r"]
TRUE_C = np.array([[0.0573, 0.0361, 0.0582, 0.0748],
                   [0.0306, -0.0442, -0.1055, -0.5035],
                   [-0.0199, 0.0210, -0.2218, 0.0346]])


def _angles(n, rng, phase):
    t = np.linspace(0, 1, n)
    return np.column_stack([np.radians(50) * (1 - np.cos(2 * np.pi * t)),
                            np.radians(4) * np.sin(2 * np.pi * t + phase),
                            np.radians(7) * np.sin(4 * np.pi * t + 2 * phase) + 0.01 * rng.standard_normal(n)])


@pytest.fixture(scope="module")
def trials(tmp_path_factory):
    """Three phantom-style truth .mot trials (angles in degrees, translations in m) of a known law."""
    rng = np.random.default_rng(11)
    d = tmp_path_factory.mktemp("kin")
    paths = []
    for i in range(3):
        A = _angles(120, rng, 0.6 * i)
        Y = A @ TRUE_C[:, :3].T + TRUE_C[:, 3] + 3e-4 * rng.standard_normal((120, 3))
        names = ["hip_flexion_r"] + IND + DEP
        vals = np.column_stack([0.2 * A[:, 0], A, Y])
        p = d / f"crouch{i}.mot"
        write_mot(p, names, np.arange(120) / 60.0, vals, in_degrees=True, rotational={"hip_flexion_r", *IND})
        paths.append(p)
    return paths


def test_correlate_recovers_law_and_writes_outputs(trials, tmp_path, capsys):
    out = tmp_path / "out"
    rc = main(["correlate", *map(str, trials), "--joint", "knee_r", "--by-trial", "--out", str(out), "--quiet"])
    assert rc == 0, capsys.readouterr().err
    law = CorrelativeLaw.from_json(out / "law.json")
    assert law.independent == tuple(IND) and law.dependent == tuple(DEP)
    rel = np.abs(law.coefficients - TRUE_C) / np.abs(TRUE_C)
    assert rel.max() < 0.02  # degrees in the files were converted: slopes per radian
    raw = json.loads((out / "law.json").read_text())
    assert raw["units"]["coefficients"] == ["m/rad", "m/rad", "m/rad", "m"]
    assert set(raw["fit"]) >= {"r2", "rms", "max_abs", "valid", "loto_rms"}
    assert min(raw["fit"]["r2"]) > 0.99
    assert raw["fit"]["n_groups"] == 3
    # Leave-one-trial-out error of an exact law is the noise level.
    np.testing.assert_allclose(raw["fit"]["loto_rms"], 3e-4, rtol=0.25)
    assert np.shape(raw["covariance"]) == (3, 4, 4)
    per = json.loads((out / "laws_by_trial.json").read_text())
    assert list(per) == ["crouch0", "crouch1", "crouch2"]
    for j in per.values():
        assert CorrelativeLaw.from_json(j).fit.n_frames == 120
    coef = list(csv.reader((out / "coefficients.csv").open()))
    assert coef[0] == ["dependent", "coefficient", "unit", "all trials", "crouch0", "crouch1", "crouch2"]
    assert len(coef) == 13
    dev = list(csv.reader((out / "deviation.csv").open()))
    assert dev[-1][0] == "all trials"
    glob, sub = (float(v) for v in dev[-1][1].split(" / "))
    # Mean 3-D deviation of isotropic noise sd s: s sqrt(8/pi) (0.48 mm); per-trial laws fit slightly closer.
    assert glob == pytest.approx(0.3 * np.sqrt(8 / np.pi), rel=0.1)
    assert sub <= glob
    assert (out / "deviation.png").read_bytes()[:4] == b"\x89PNG"
    md = (out / "tables.md").read_text()
    assert "seed Table 1 form" in md and "motion specific / sub-motion specific" in md


def test_correlate_fluoroscopy_with_explicit_columns(shared_data, tmp_path, capsys):
    sto = shared_data / "knee_fluoroscopy" / "DM_fluoroscopic_gait_knee6dof.sto"
    out = tmp_path / "fluoro"
    rc = main(["correlate", str(sto), "--independent", "knee_rot_r,knee_add_r,knee_flex_r",
               "--dependent", "knee_ant_r,knee_sup_r,knee_lat_r", "--out", str(out)])
    assert rc == 0, capsys.readouterr().err
    law = CorrelativeLaw.from_json(out / "law.json")
    tab = read_sto(sto)
    ref = fit_law(tab.select(list(law.independent)), tab.select(list(law.dependent)))
    np.testing.assert_allclose(law.coefficients, ref.coefficients, atol=1e-12)
    np.testing.assert_allclose(law.fit.r2, ref.fit.r2)
    assert law.fit.n_frames == 101


@pytest.mark.parametrize("args, message", [
    (["--dependent", "knee_tx_r,knee_flexion_r"], "listed both as dependent and independent"),
    (["--independent", "knee_flexion_r,knee_bogus_r"], "missing columns: knee_bogus_r"),
])
def test_correlate_bad_columns(trials, tmp_path, capsys, args, message):
    out = tmp_path / "bad"
    rc = main(["correlate", str(trials[0]), "--out", str(out), "--quiet", *args])
    err = capsys.readouterr().err
    assert rc == 2 and message in err and err.startswith("error: ")
    assert not out.exists()


def test_correlate_missing_default_columns_and_file_type(tmp_path, capsys):
    p = tmp_path / "other.mot"
    write_mot(p, ["a_r", "b_r"], np.arange(10.0), np.ones((10, 2)), in_degrees=False)
    rc = main(["correlate", str(p), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 2 and "missing columns: knee_flexion_r" in err and "--independent" in err
    q = tmp_path / "x.csv"
    q.write_text("1,2\n")
    assert main(["correlate", str(q), "--out", str(tmp_path / "o")]) == 2
    assert "unsupported kinematics file type" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_correlate_degenerate_data(tmp_path, capsys):
    names = IND + DEP
    rng = np.random.default_rng(12)
    # Fewer frames than coefficients.
    p = tmp_path / "short.mot"
    write_mot(p, names, np.arange(3.0), rng.normal(size=(3, 6)), in_degrees=False)
    assert main(["correlate", str(p), "--out", str(tmp_path / "o1"), "--quiet"]) == 2
    assert "3 frames for 4 coefficients" in capsys.readouterr().err
    # An independent coordinate that does not vary (rank-deficient design).
    vals = rng.normal(size=(50, 6))
    vals[:, 1] = 0.1
    p = tmp_path / "flat.mot"
    write_mot(p, names, np.arange(50.0), vals, in_degrees=False)
    assert main(["correlate", str(p), "--out", str(tmp_path / "o2"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "knee_adduction_r do not vary" in err and "rank deficient" in err
    assert not (tmp_path / "o1").exists() and not (tmp_path / "o2").exists()


def test_correlate_blocked_folds(trials, tmp_path, capsys):
    out = tmp_path / "folds"
    assert main(["correlate", str(trials[0]), "--folds", "4", "--out", str(out), "--quiet"]) == 0
    raw = json.loads((out / "law.json").read_text())
    assert raw["fit"]["n_groups"] == 4 and raw["data"]["cross_validation"].startswith("4 contiguous")
    # Held-out blocks of an exact linear law: error near the noise, never below the in-sample rms by much.
    assert np.all(np.asarray(raw["fit"]["loto_rms"]) < 3 * 3e-4)
    assert np.all(np.asarray(raw["fit"]["loto_rms"]) > 0.9 * np.asarray(raw["fit"]["rms"]))
    assert main(["correlate", str(trials[0]), "--folds", "1", "--out", str(tmp_path / "f1"), "--quiet"]) == 2
    assert "--folds" in capsys.readouterr().err


def test_joint_law_from_a_script(trials, tmp_path):
    """The library form of the command: fit_joint_law recovers the law, write_joint_law writes it losslessly."""
    from personalize.correlative_laws import fit_joint_law, law_document, write_joint_law

    fit = fit_joint_law(trials, joint="knee_r", folds=4)
    assert fit.labels == ("crouch0", "crouch1", "crouch2") and fit.frames == dict.fromkeys(fit.labels, 120)
    assert fit.independent.shape == (360, 3) and not fit.trial_laws
    assert (np.abs(fit.law.coefficients - TRUE_C) / np.abs(TRUE_C)).max() < 0.02
    assert law_document(fit)["data"]["cross_validation"] == "4 contiguous blocks per trial"
    out = write_joint_law(fit, tmp_path / "law")
    assert sorted(p.name for p in out.iterdir()) == ["coefficients.csv", "deviation.csv", "deviation.png", "fit.csv",
                                                     "law.json", "tables.md"]
    np.testing.assert_allclose(CorrelativeLaw.from_json(out / "law.json").coefficients, fit.law.coefficients,
                               rtol=0, atol=1e-15)
