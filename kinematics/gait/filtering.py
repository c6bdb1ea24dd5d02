"""Low-pass filtering and differentiation of gait signals (markers, coordinates, forces).

Two zero-lag Butterworth low-pass filters, both run forward then backward
(the magnitude response is squared, the phase cancels):

``method="winter"`` (default)
    An ``order``-th order Butterworth (scipy.signal.butter, second-order
    sections, ``sosfiltfilt`` with odd padding), its cut-off raised so that the
    DOUBLE pass is -3 dB at the requested ``cutoff`` (Winter 2009, sec. 3.4.4;
    Robertson & Dowling 2003).  With the bilinear transform's warped
    frequency Omega = tan(pi f / f_s), a single pass is
    |H|^2 = 1 / (1 + (Omega / Omega_c)^(2 n)); the double pass |H|^2 = 1/sqrt(2)
    at f_0 when

        Omega_c = tan(pi f_0 / f_s) / (sqrt(2) - 1)^(1 / (2 n)).

``method="opensim"``
    OpenSim's ``InverseDynamicsTool`` filtering of the coordinates, step for
    step (``Storage::pad(N/2)`` then ``Signal::LowpassIIR``): the signal is
    padded at both ends with N/2 samples reflected about the end value (value
    and slope kept), then a 3rd-order Butterworth designed by the same bilinear
    transform at ``cutoff`` itself (no double-pass correction: the result is
    -6 dB at the cut-off) runs forward and backward, the first three
    samples of each pass passed through unfiltered as OpenSim does.

`residual_analysis` picks a cut-off by Winter's residual analysis;
`derivatives` differentiates sampled signals with OpenSim's interpolating
quintic spline (GCVSPL with zero error variance = natural quintic spline,
knots at the samples: third and fourth derivatives zero at the ends), which
is what the InverseDynamicsTool uses for velocities and accelerations.

All functions filter along axis 0 (time).  `lowpass` refuses NaN;
`lowpass_runs` and `filter_markers` filter each gap-free run of a signal on
its own and leave the gaps NaN (fill short gaps first with
`kinematics.io.c3d.fill_gaps` to keep runs long).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kinematics.io.markers import true_runs
from lowerlimb.errors import InputError

__all__ = ["DEFAULT_CUTOFF_HZ", "ResidualAnalysis", "choose_cutoff", "corrected_cutoff", "derivatives",
           "filter_markers", "lowpass", "lowpass_runs", "residual_analysis"]

DEFAULT_CUTOFF_HZ = 6.0


def _check(x, rate, cutoff, source="signal"):
    x = np.asarray(x, float)
    if x.ndim == 0 or x.shape[0] < 2:
        raise InputError(source, "at least 2 samples are needed to filter")
    if not np.all(np.isfinite(x)):
        raise InputError(source, "signal has NaN or infinite samples; fill the gaps before filtering")
    if not rate > 0:
        raise InputError("rate", f"sampling rate must be positive, got {rate}")
    if not 0 < cutoff < 0.5 * rate:
        raise InputError("cutoff", f"cut-off {cutoff} Hz must be between 0 and half the sampling rate ({0.5 * rate:g} Hz)")
    return x


def corrected_cutoff(cutoff: float, rate: float, order: int = 2, passes: int = 2) -> float:
    """Cut-off (Hz) to design one pass with so that `passes` passes are -3 dB at `cutoff`."""
    w0 = np.tan(np.pi * cutoff / rate)
    wc = w0 / (2.0 ** (1.0 / passes) - 1.0) ** (1.0 / (2 * order))
    return float(np.arctan(wc) * rate / np.pi)


def lowpass(x, rate: float, cutoff: float = DEFAULT_CUTOFF_HZ, *, order: int = 2, method: str = "winter",
            source: str = "signal") -> np.ndarray:
    """Zero-lag Butterworth low-pass of `x` (F, ...) sampled at `rate` Hz, along time (axis 0).

    Parameters
    ----------
    x : ndarray (F, ...)
    rate : float, Hz
    cutoff : float, Hz
        -3 dB frequency of the whole (double-pass) filter for ``"winter"``;
        OpenSim's single-pass cut-off for ``"opensim"``.
    order : int
        Order of one pass (``"winter"``; ``"opensim"`` is always 3).
    method : {"winter", "opensim"}

    Returns
    -------
    ndarray, same shape as `x`.
    """
    from scipy import signal

    x = _check(x, rate, cutoff, source)
    if method == "winter":
        fc = corrected_cutoff(cutoff, rate, order)
        if not fc < 0.5 * rate:
            raise InputError("cutoff", f"cut-off {cutoff} Hz is too close to the Nyquist frequency for a double pass")
        sos = signal.butter(order, fc, btype="low", fs=rate, output="sos")
        n = x.shape[0]
        # odd padding over three cut-off periods (scipy's default, 3 sections' length, leaves 4x larger
        # end transients on gait signals)
        padlen = min(max(3 * (2 * len(sos) + 1), round(3 * rate / cutoff)), n - 1)
        return signal.sosfiltfilt(sos, x, axis=0, padtype="odd", padlen=padlen)
    if method == "opensim":
        return _opensim_lowpass(x, rate, cutoff)
    raise InputError("method", f"must be 'winter' or 'opensim', got {method!r}")


def _opensim_lowpass(x: np.ndarray, rate: float, cutoff: float, padded: bool = False) -> np.ndarray:
    """OpenSim's pad + LowpassIIR; with `padded` the N//2 padding samples stay at both ends."""
    n = x.shape[0]
    pad = n // 2
    if pad > 0:
        head = 2.0 * x[0] - x[pad:0:-1]
        tail = 2.0 * x[-1] - x[-2:-pad - 2:-1]
        s = np.concatenate([head, x, tail], axis=0)
    else:
        s = x.copy()
    wa = np.tan(np.pi * cutoff / rate)
    wa2, wa3 = wa * wa, wa ** 3
    den = (wa + 1.0) * (wa2 + wa + 1.0)
    a = np.array([wa3, 3 * wa3, 3 * wa3, wa3]) / den
    b = np.array([1.0, (3 * wa3 + 2 * wa2 - 2 * wa - 3) / den, (3 * wa3 - 2 * wa2 - 2 * wa + 3) / den,
                  (wa - 1.0) * (wa2 - wa + 1.0) / den])

    from scipy.signal import lfilter

    def one_pass(sig):
        # OpenSim passes the first three samples through and starts the recurrence at sample 3:
        # lfilter (direct form II transposed) on sig[3:] from the state those samples leave
        # (inputs and outputs both sig[0:3]).
        out = sig.copy()
        if sig.shape[0] <= 3:
            return out
        x0, x1, x2 = sig[0], sig[1], sig[2]
        zi = np.stack([(a[1] - b[1]) * x2 + (a[2] - b[2]) * x1 + (a[3] - b[3]) * x0,
                       (a[2] - b[2]) * x2 + (a[3] - b[3]) * x1,
                       (a[3] - b[3]) * x2])
        out[3:], _ = lfilter(a, b, sig[3:], axis=0, zi=zi)
        return out

    y = one_pass(one_pass(s)[::-1])[::-1]
    return y if padded else y[pad:pad + n]


def derivatives(x, time, order: int = 2) -> list[np.ndarray]:
    """Value and derivatives up to `order` of an interpolating natural quintic spline through (time, x).

    Returns
    -------
    list of ndarray (F, ...): [x, dx/dt, d2x/dt2, ...] at the sample times
    (the first equals `x`).
    """
    from scipy.interpolate import make_interp_spline

    x = np.asarray(x, float)
    t = np.asarray(time, float)
    if t.ndim != 1 or t.shape[0] != x.shape[0]:
        raise InputError("time", f"{t.shape[0] if t.ndim == 1 else t.shape} times for {x.shape[0]} samples")
    if t.shape[0] < 6:
        raise InputError("time", "a quintic spline needs at least 6 samples")
    if np.any(np.diff(t) <= 0):
        raise InputError("time", "times must increase strictly")
    zeros = np.zeros(x.shape[1:])
    bc = ([(3, zeros), (4, zeros)], [(3, zeros), (4, zeros)])
    spl = make_interp_spline(t, x, k=5, bc_type=bc, axis=0)
    return [spl(t, nu=k) for k in range(order + 1)]


@dataclass(frozen=True)
class ResidualAnalysis:
    """Winter's residual analysis of one signal.

    Attributes
    ----------
    cutoffs : ndarray (K,), Hz
    residuals : ndarray (K,)
        R(f_c) = sqrt(mean((x - x_fc)^2)), signal units.
    noise : float
        Intercept at f_c = 0 of the line fitted to the high-frequency residuals
        (the residual white noise alone would leave).
    cutoff : float, Hz
        Lowest f_c with R(f_c) <= noise.
    """

    cutoffs: np.ndarray
    residuals: np.ndarray
    noise: float
    cutoff: float


def residual_analysis(x, rate: float, cutoffs=None, *, fit_from: float | None = None, order: int = 2) -> ResidualAnalysis:
    """Cut-off frequency by Winter's residual analysis (Winter 2009, sec. 3.4.4.3).

    For each candidate f_c the residual R(f_c) between the raw and filtered
    signal (RMS over samples and channels) is computed.  Above the signal's
    band, R falls linearly with f_c (white noise); a line fitted to R over
    [`fit_from`, max f_c] (default: the upper half of the candidates) is
    extrapolated to f_c = 0, its intercept a is the noise residual, and the
    chosen cut-off is where R(f_c) first drops to a (linear interpolation
    between candidates).

    Parameters
    ----------
    x : ndarray (F, ...) sampled at `rate`
    cutoffs : increasing candidate cut-offs (Hz); default 0.5 Hz steps from 1 Hz to 0.4 rate (at most 25 Hz)
    """
    x = np.asarray(x, float)
    fc = _candidates(cutoffs, rate)
    res = np.sqrt(np.mean(_residuals(x.reshape(x.shape[0], -1), rate, fc, order) ** 2, axis=1))
    return _pick(fc, res, fit_from)


def _candidates(cutoffs, rate):
    if cutoffs is None:
        cutoffs = np.arange(1.0, min(25.0, 0.4 * rate) + 1e-9, 0.5)
    fc = np.asarray(cutoffs, float)
    if fc.ndim != 1 or fc.size < 4 or np.any(np.diff(fc) <= 0):
        raise InputError("cutoffs", "need at least 4 increasing candidate cut-offs")
    return fc


def _residuals(x2: np.ndarray, rate: float, fc: np.ndarray, order: int, method: str = "winter") -> np.ndarray:
    """Per candidate cut-off and channel, the RMS over samples of x - lowpass(x): (K, C)."""
    return np.stack([np.sqrt(np.mean((x2 - lowpass(x2, rate, f, order=order, method=method)) ** 2, axis=0))
                     for f in fc])


def _pick(fc: np.ndarray, res: np.ndarray, fit_from) -> ResidualAnalysis:
    lo = fit_from if fit_from is not None else fc[fc.size // 2]
    sel = fc >= lo
    if sel.sum() < 2:
        raise InputError("fit_from", f"fewer than 2 candidate cut-offs above {lo} Hz")
    _, intercept = np.polyfit(fc[sel], res[sel], 1)
    noise = float(max(intercept, 0.0))
    below = np.flatnonzero(res <= noise)
    if below.size == 0:
        chosen = float(fc[-1])
    elif below[0] == 0:
        chosen = float(fc[0])
    else:
        k = below[0]
        r0, r1 = res[k - 1], res[k]
        chosen = float(fc[k - 1] + (r0 - noise) / (r0 - r1) * (fc[k] - fc[k - 1]))
    return ResidualAnalysis(fc, res, noise, chosen)


def choose_cutoff(x, rate: float, cutoffs=None, *, method: str = "winter") -> tuple[float, np.ndarray]:
    """One cut-off for several channels: the median of their residual-analysis cut-offs.

    Channels that do not move (range under 1e-9) are skipped.  Returns the
    chosen cut-off (Hz) and the per-channel cut-offs (NaN for skipped ones).
    The residuals are those of the filter that will be applied (`method` of
    `lowpass`): a cut-off chosen with one filter means another with another.
    """
    x = np.asarray(x, float)
    x2 = x.reshape(x.shape[0], -1)
    per = np.full(x2.shape[1], np.nan)
    moving = np.ptp(x2, axis=0) > 1e-9
    if not moving.any():
        raise InputError("cutoff", "no channel moves: a residual analysis cannot choose a cut-off")
    fc = _candidates(cutoffs, rate)
    res = _residuals(x2[:, moving], rate, fc, 2, method)  # all channels filtered together per candidate
    per[moving] = [_pick(fc, res[:, j], None).cutoff for j in range(res.shape[1])]
    return float(np.nanmedian(per)), per


def lowpass_runs(x, rate: float, cutoff: float = DEFAULT_CUTOFF_HZ, *, order: int = 2, method: str = "winter",
                 min_samples: int = 4) -> np.ndarray:
    """`lowpass` of every gap-free run of `x` (F, ...) on its own; NaN samples stay NaN.

    A sample is missing when any of its components (trailing axes) is not
    finite.  Runs shorter than `min_samples` cannot be filtered and become NaN
    (a filter with no context would return them unchanged, i.e. unfiltered).
    """
    x = np.asarray(x, float)
    ok = np.all(np.isfinite(x.reshape(x.shape[0], -1)), axis=1)
    out = np.full_like(x, np.nan)
    for a, b in true_runs(ok):
        if b - a >= min_samples:
            out[a:b] = lowpass(x[a:b], rate, cutoff, order=order, method=method)
    return out


def filter_markers(trial, cutoff: float = DEFAULT_CUTOFF_HZ, *, order: int = 2):
    """A `MarkerTrial` with every marker low-passed (Winter's double pass) run by run; gaps stay NaN."""
    from kinematics.io.markers import MarkerTrial

    pos = np.stack([lowpass_runs(trial.positions[:, j], trial.rate, cutoff, order=order)
                    for j in range(len(trial.names))], axis=1)
    extra = dict(trial.extra)
    extra["lowpass_hz"] = float(cutoff)
    return MarkerTrial(trial.names, pos, trial.rate, trial.time, trial.source, extra)
