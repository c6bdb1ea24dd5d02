"""Filtering and differentiation: analytic responses, Winter's residual analysis, OpenSim's own filter and splines."""
from __future__ import annotations

import numpy as np
import pytest

from lowerlimb.errors import InputError
from kinematics.gait.filtering import (
    corrected_cutoff,
    derivatives,
    lowpass,
    residual_analysis,
)


def _amplitude(y, x):
    mid = slice(len(x) // 4, 3 * len(x) // 4)
    return np.std(y[mid]) / np.std(x[mid])


@pytest.mark.parametrize("order", [2, 4])
def test_winter_double_pass_is_minus_3db_at_cutoff_and_zero_lag(order):
    fs, fc = 100.0, 6.0
    t = np.arange(2000) / fs
    at_fc = np.sin(2 * np.pi * fc * t)
    assert _amplitude(lowpass(at_fc, fs, fc, order=order), at_fc) == pytest.approx(1 / np.sqrt(2), abs=5e-3)
    slow = np.sin(2 * np.pi * 1.0 * t)
    y = lowpass(slow, fs, fc, order=order)
    assert _amplitude(y, slow) > 0.995
    # zero lag: the filtered slow sine crosses zero where the input does
    mid = slice(500, 1500)
    assert np.abs(y[mid] - slow[mid]).max() < 0.01
    fast = np.sin(2 * np.pi * 20.0 * t)
    assert _amplitude(lowpass(fast, fs, fc, order=order), fast) < 0.05
    assert corrected_cutoff(fc, fs, order) > fc


def test_opensim_method_matches_opensim_storage_filter(shared_data, opensim, tmp_path):
    """OpenSim's InverseDynamicsTool filtering (Storage.pad(N/2) + lowpassIIR) on the subject01 IK result."""
    from kinematics.io.storage import read_mot

    path = shared_data / "opensim_gait2392" / "subject01_walk1_ik.mot"
    tab = read_mot(path)
    st = opensim.Storage(str(path))
    st.pad(st.getSize() // 2)
    st.lowpassIIR(6.0)
    n0 = tab.n_frames // 2
    ours = lowpass(tab.values, 1.0 / np.mean(np.diff(tab.time)), 6.0, method="opensim")
    labels = st.getColumnLabels()
    for j, name in enumerate(tab.columns[:8]):
        col = opensim.ArrayDouble()
        st.getDataColumn(labels.findIndex(name) - 1, col)
        ref = np.array([col.get(i) for i in range(col.getSize())])[n0:n0 + tab.n_frames]
        scale = max(np.abs(tab.values[:, j]).max(), 1e-9)
        # OpenSim resamples at the smallest time step of the file (times rounded to 8 decimals): 1e-5 of range
        assert np.abs(ours[:, j] - ref).max() < 2e-5 * scale, name
    # and it filters: the 6 Hz 3rd-order double pass is -6 dB at the cut-off
    t = np.arange(1200) / 60.0
    x = np.sin(2 * np.pi * 6.0 * t)
    assert _amplitude(lowpass(x, 60.0, 6.0, method="opensim"), x) == pytest.approx(0.5, abs=0.01)


def test_derivatives_match_opensim_gcv_spline(opensim, tmp_path):
    from kinematics.io.storage import write_sto

    t = np.arange(60) / 60.0
    x = np.column_stack([np.sin(2 * np.pi * 1.5 * t) + 0.3 * t ** 2, np.cos(2 * np.pi * 0.7 * t)])
    write_sto(tmp_path / "s.sto", ["a", "b"], t, x)
    spl = opensim.GCVSplineSet(5, opensim.Storage(str(tmp_path / "s.sto")))
    y, yd, ydd = derivatives(x, t, 2)
    assert np.allclose(y, x)

    # OpenSim's spline derivatives by central differences of its values: calcDerivative takes a
    # std::vector<int> whose SWIG type is ambiguous once several opensim modules are loaded in a worker
    def value(f, tk):
        return f.calcValue(opensim.Vector(1, float(tk)))

    inside = range(1, len(t) - 1)
    for j in range(2):
        f = spl.get(j)
        h1, h2 = 1e-6, 1e-4
        d1 = [(value(f, t[k] + h1) - value(f, t[k] - h1)) / (2 * h1) for k in inside]
        d2 = [(value(f, t[k] + h2) - 2 * value(f, t[k]) + value(f, t[k] - h2)) / h2 ** 2 for k in inside]
        assert np.abs(np.array(d1) - yd[1:-1, j]).max() < 1e-5 * np.abs(yd[:, j]).max()
        assert np.abs(np.array(d2) - ydd[1:-1, j]).max() < 1e-4 * np.abs(ydd[:, j]).max()
    # analytic interior check
    inner = slice(5, -5)
    assert np.allclose(yd[inner, 0], (2 * np.pi * 1.5 * np.cos(2 * np.pi * 1.5 * t) + 0.6 * t)[inner], rtol=0, atol=1e-3)


def test_residual_analysis_finds_noise_level():
    rng = np.random.default_rng(3)
    fs = 200.0
    t = np.arange(1000) / fs
    clean = np.sin(2 * np.pi * 1.0 * t) + 0.4 * np.sin(2 * np.pi * 3.0 * t + 1.0)
    sigma = 0.01
    ra = residual_analysis(clean + rng.normal(0, sigma, t.shape), fs)
    assert ra.noise == pytest.approx(sigma, rel=0.25)
    assert 3.0 < ra.cutoff < 12.0  # above the signal's 3 Hz, well below the 100 Hz Nyquist
    # the chosen cut-off recovers the clean signal better than the noisy samples are
    rec = lowpass(clean + rng.normal(0, sigma, t.shape), fs, ra.cutoff)
    assert np.sqrt(np.mean((rec - clean)[50:-50] ** 2)) < 0.5 * sigma


def test_bad_input_refused():
    with pytest.raises(InputError, match="NaN"):
        lowpass(np.array([0.0, 1.0, np.nan, 2.0]), 100.0, 6.0)
    with pytest.raises(InputError, match="half the sampling rate"):
        lowpass(np.zeros(50), 10.0, 6.0)
    with pytest.raises(InputError, match="method"):
        lowpass(np.zeros(50), 100.0, 6.0, method="median")


def test_choose_cutoff_on_real_ik(shared_data):
    """Residual analysis of subject01's IK coordinates: gait's 4-12 Hz band (Winter: 4-8 Hz for walking
    markers; IK joint angles carry some less noise), mtp (locked, constant) skipped."""
    from kinematics.gait.filtering import choose_cutoff
    from kinematics.io.storage import read_mot

    tab = read_mot(shared_data / "opensim_gait2392" / "subject01_walk1_ik.mot")
    fc, per = choose_cutoff(tab.values, 60.0)
    assert 4.0 < fc < 12.0
    mtp = [j for j, c in enumerate(tab.columns) if c.startswith("mtp")]
    assert np.isnan(per[mtp]).all() and np.isfinite(np.delete(per, mtp)).all()
    # the analysis uses the filter it is chosen for: OpenSim's filter is -6 dB at its cut-off (Winter's -3 dB),
    # so the same residual needs a higher OpenSim cut-off
    fo, _ = choose_cutoff(tab.values, 60.0, method="opensim")
    assert fo > 1.03 * fc   # 8.11 vs 7.73 Hz


def test_filter_markers_run_by_run(shared_data):
    """mocap_pig's movement markers (already smooth, as Nexus exports them) plus 1 mm of white noise per axis:
    the 6 Hz filter removes most of it (median over the 115 markers: 0.42 of the noise's RMS left, including
    the filter's own smoothing of fast segments; every marker below the noise); gaps stay NaN."""
    from kinematics.io.c3d import read_c3d
    from kinematics.gait.filtering import filter_markers, lowpass_runs
    from kinematics.io.markers import MarkerTrial

    mk = read_c3d(shared_data / "mocap_pig" / "Movement_trial.c3d")
    noise = np.random.default_rng(7).normal(0, 1e-3, mk.positions.shape)
    f = filter_markers(MarkerTrial(mk.names, mk.positions + noise, mk.rate, mk.time), 6.0)
    assert f.extra["lowpass_hz"] == 6.0
    assert np.array_equal(np.isnan(f.positions), np.isnan(mk.positions))
    err = np.linalg.norm(f.positions - mk.positions, axis=2)
    ref = np.where(np.isnan(err), np.nan, np.linalg.norm(noise, axis=2))
    ratio = np.sqrt(np.nanmean(err ** 2, axis=0)) / np.sqrt(np.nanmean(ref ** 2, axis=0))
    assert np.nanmedian(ratio) < 0.5 and np.nanmax(ratio) < 1.0
    # a gap splits the signal: both runs filtered, the gap and a too-short run stay NaN
    x = np.sin(np.linspace(0, 6, 200))[:, None].repeat(3, axis=1)
    x[50:60] = np.nan
    x[61] = np.nan
    y = lowpass_runs(x, 100.0, 6.0)
    assert np.isnan(y[50:62]).all() and np.isfinite(y[:50]).all() and np.isfinite(y[62:]).all()
