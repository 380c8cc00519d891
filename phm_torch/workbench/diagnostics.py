"""Where the model fails: error metrics, worst windows, residual maps in physical coordinates, spectra and
the classical residual tests (whiteness, residual-input cross-correlation).

Everything works on numpy arrays per record {channel: (n,)}. Residual maps use the calibrated model's
motor speed and rotor angle (the states the residual is aligned with) and the measured current.
Conventions: NRMSE = RMS(simulated - measured) / range(measured) (a fraction); fit % = 100 (1 -
||error|| / ||measured - mean||) (as MATLAB ``compare``); the noise floor is sigma / range, the NRMSE of
a perfect model; totals are root-mean-squares over the compared channels.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy import stats
from scipy.signal import welch

from .. import checks

PerRecord = Sequence[Mapping[str, np.ndarray]]


@dataclass(frozen=True)
class DiagnosticSettings:
    """Attributes: window [s] and count of worst windows; bins of the maps; max_harmonic (mechanical
    order; ``None``: twice the actuator's highest structural order, see :func:`~.orders.max_order`);
    max_lag [samples] of the correlation plots; whiteness_lags for the Ljung-Box test; reversal
    half-window [s]; alpha of the tests; fidelity_gap: at LF fidelity, when nothing in the library explains the
    residual, simulate the final model at HF too (one HF run a record) and report how far the two differ against the
    noise floor (:mod:`~.fidelity_gap`)."""

    window: float = 0.025
    worst: int = 5
    bins: int = 24
    max_harmonic: int | None = None
    max_lag: int = 200
    whiteness_lags: int = 50
    reversal_window: float = 0.01
    alpha: float = 0.01
    fidelity_gap: bool = True

    def __post_init__(self) -> None:
        if not isinstance(self.fidelity_gap, bool):
            raise ValueError(f"diagnostics.fidelity_gap must be true or false, got {self.fidelity_gap!r}")
        for name in ("worst", "bins", "max_harmonic", "max_lag", "whiteness_lags"):
            if getattr(self, name) is None and name == "max_harmonic":
                continue
            object.__setattr__(self, name, checks.integer(getattr(self, name), f"diagnostics.{name}", 1))
        for name in ("window", "reversal_window"):
            object.__setattr__(self, name, checks.number(getattr(self, name), f"diagnostics.{name}", 0.0, True))
        alpha = checks.number(self.alpha, "diagnostics.alpha")
        if not 0 < alpha < 1:
            raise ValueError(f"diagnostics.alpha must be in (0, 1), got {self.alpha!r}")
        object.__setattr__(self, "alpha", alpha)


def pooled(values: Sequence[float], weights: Sequence[float]) -> float:
    """sqrt(sum w v^2 / sum w): pool per-record fractions over records of different lengths."""
    w = np.asarray(weights, dtype=np.float64)
    return float(np.sqrt(np.sum(w * np.asarray(values) ** 2) / np.sum(w)))


def error_metrics(errors: PerRecord, measured: PerRecord, sigma: Sequence[Mapping[str, float]]) -> dict:
    """NRMSE, fit % and noise floor per channel and in total.

    Args:
        errors: per record {channel: simulated - measured (n,)}.  measured: per record {channel: (n,)}.
        sigma: per record {channel: noise std}.
    Returns:
        {"nrmse": {ch..., "total"}, "fit_percent": {ch...}, "noise_floor": {ch..., "total"},
        "noise_std": {ch: pooled std}}.
    """
    chans = list(errors[0])
    lengths = [len(next(iter(e.values()))) for e in errors]
    out: dict[str, dict[str, float]] = {"nrmse": {}, "fit_percent": {}, "noise_floor": {}, "noise_std": {}}
    for c in chans:
        ranges = [float(np.ptp(m[c])) for m in measured]
        out["nrmse"][c] = pooled([np.sqrt(np.mean(e[c] ** 2)) / r for e, r in zip(errors, ranges)], lengths)
        num = sum(float(np.sum(e[c] ** 2)) for e in errors)
        den = sum(float(np.sum((m[c] - m[c].mean()) ** 2)) for m in measured)
        out["fit_percent"][c] = 100.0 * (1.0 - math.sqrt(num / den))
        out["noise_floor"][c] = pooled([s[c] / r for s, r in zip(sigma, ranges)], lengths)
        out["noise_std"][c] = pooled([s[c] for s in sigma], lengths)
    for key in ("nrmse", "noise_floor"):
        out[key]["total"] = float(np.sqrt(np.mean([out[key][c] ** 2 for c in chans])))
    return out


def worst_windows(
    errors: PerRecord, measured: PerRecord, names: Sequence[str], sample_rate: float, window: float, count: int
) -> list[dict]:
    """The ``count`` non-overlapping windows of largest NRMSE (RMS over the window / record range, total over
    channels), each {record, t_start, t_end, nrmse, channels: {ch: nrmse}}, worst first."""
    width = max(2, round(window * sample_rate))
    hop = max(1, width // 2)
    cands = []
    for i, (err, meas) in enumerate(zip(errors, measured)):
        n = len(next(iter(err.values())))
        per = {}
        for c, e in err.items():
            csum = np.concatenate([[0.0], np.cumsum(e**2)])
            starts = np.arange(0, max(n - width, 0) + 1, hop)
            per[c] = np.sqrt((csum[np.minimum(starts + width, n)] - csum[starts]) / width) / np.ptp(meas[c])
        total = np.sqrt(np.mean(np.stack(list(per.values())) ** 2, axis=0))
        for k, s in enumerate(starts):
            cands.append((float(total[k]), i, int(s), {c: float(v[k]) for c, v in per.items()}))
    cands.sort(key=lambda t: -t[0])
    chosen: list[tuple] = []
    for cand in cands:
        if all(cand[1] != o[1] or abs(cand[2] - o[2]) >= width for o in chosen):
            chosen.append(cand)
        if len(chosen) == count:
            break
    return [
        {
            "record": names[i],
            "t_start": s / sample_rate,
            "t_end": (s + width - 1) / sample_rate,
            "nrmse": v,
            "channels": ch,
        }
        for v, i, s, ch in chosen
    ]


def _binned(x: np.ndarray, y: np.ndarray, edges: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean, standard error and count of y in the bins of x."""
    idx = np.clip(np.digitize(x, edges) - 1, 0, len(edges) - 2)
    inside = (x >= edges[0]) & (x <= edges[-1])
    k = len(edges) - 1
    cnt = np.bincount(idx[inside], minlength=k).astype(np.float64)
    s1 = np.bincount(idx[inside], y[inside], minlength=k)
    s2 = np.bincount(idx[inside], y[inside] ** 2, minlength=k)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(cnt > 0, s1 / np.maximum(cnt, 1), np.nan)
        var = np.where(cnt > 1, (s2 - cnt * mean**2) / np.maximum(cnt - 1, 1), np.nan)
        se = np.sqrt(np.maximum(var, 0) / np.maximum(cnt, 1))
    return mean, se, cnt


def reversals(speed: np.ndarray, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """Indices where the motor speed reverses (+ to - and - to +), ignoring excursions below ``threshold``."""
    sign = np.where(speed > threshold, 1, np.where(speed < -threshold, -1, 0))
    nz = np.flatnonzero(sign)
    if nz.size < 2:
        return np.array([], dtype=int), np.array([], dtype=int)
    s = sign[nz]
    change = np.flatnonzero(np.diff(s) != 0)
    idx = (nz[change] + nz[change + 1]) // 2  # middle of the slow (or stuck) interval
    return idx[s[change] > 0], idx[s[change] < 0]


@dataclass
class Coordinates:
    """Physical coordinates of one record, each (n,): motor speed [rad/s], motor angle [rad] (model), current
    magnitude [A] (measured) and the sign of the motor torque (model), which is the sign of the current whose
    magnitude the envelope channel measures."""

    speed: np.ndarray
    motor_angle: np.ndarray
    current: np.ndarray
    torque_sign: np.ndarray

    def demodulated(self, channel: str, values: np.ndarray) -> np.ndarray:
        """Values of a channel with the envelope's sign flips undone (``current`` only): a torque ripple then
        keeps its rotor-angle order instead of being split by every change of torque direction."""
        return values * self.torque_sign if channel == "current" else values


def profiles(
    values: PerRecord, coords: Sequence[Coordinates], settings: DiagnosticSettings, pole_pairs: int, sample_rate: float
) -> dict[str, dict]:
    """Binned maps of per-record signals {channel: (n,)} (e.g. normalised residuals).

    Returns {map: {"x": bin centres, "unit": ..., channel: {"mean", "se", "count"} or per-branch dicts}} for
    the maps ``speed`` (|motor speed|, split by sign), ``reversal`` (time from a velocity reversal, per
    direction), ``mechanical_angle`` (rotor angle in [-pi, pi)) and ``electrical_angle`` (mod 2 pi), ``current``
    (measured current magnitude) and ``time``.
    """
    chans = list(values[0])
    cat = {c: np.concatenate([v[c] for v in values]) for c in chans}
    spd = np.concatenate([k.speed for k in coords])
    ang = np.concatenate([k.motor_angle for k in coords])
    cur = np.concatenate([np.abs(k.current) for k in coords])
    tim = np.concatenate([np.arange(len(k.speed)) / sample_rate for k in coords])
    b = settings.bins
    out: dict[str, dict] = {}
    moving = np.abs(spd) > 1e-9
    top = float(np.abs(spd).max()) if moving.any() else 1.0
    edges = np.linspace(0.0, top, b + 1)
    out["speed"] = {"x": 0.5 * (edges[1:] + edges[:-1]), "unit": "rad/s"}
    for c in chans:
        out["speed"][c] = {}
        for branch, sel in (("positive", spd > 1e-9), ("negative", spd < -1e-9)):
            m, se, n = _binned(np.abs(spd[sel]), cat[c][sel], edges)
            out["speed"][c][branch] = {"mean": m, "se": se, "count": n}
    half = max(1, round(settings.reversal_window * sample_rate))
    lag_edges = np.linspace(-half - 0.5, half + 0.5, 2 * b + 1)
    lag_bin = np.clip(np.digitize(np.arange(-half, half + 1), lag_edges) - 1, 0, 2 * b - 1)
    out["reversal"] = {"x": 0.5 * (lag_edges[1:] + lag_edges[:-1]) / sample_rate, "unit": "s"}
    thr = 0.02 * top
    for c in chans:
        out["reversal"][c] = {}
        for branch, pick in (("pos_to_neg", 0), ("neg_to_pos", 1)):
            segs = []
            for v, k in zip(values, coords, strict=True):
                for i in reversals(k.speed, thr)[pick]:
                    if i - half >= 0 and i + half < len(k.speed):
                        segs.append(v[c][i - half : i + half + 1])
            if segs:
                per_lag = np.stack(segs).mean(0)
                mean = np.bincount(lag_bin, per_lag, minlength=2 * b) / np.bincount(lag_bin, minlength=2 * b)
            else:
                mean = np.full(2 * b, np.nan)
            out["reversal"][c][branch] = {"mean": mean, "count": np.full(2 * b, float(len(segs)))}
    two_pi = 2 * math.pi
    for name, theta, lo in (
        ("mechanical_angle", np.mod(ang + math.pi, two_pi) - math.pi, -math.pi),
        ("electrical_angle", np.mod(pole_pairs * ang, two_pi), 0.0),
    ):
        edges = np.linspace(lo, lo + two_pi, 4 * b + 1)
        out[name] = {"x": 0.5 * (edges[1:] + edges[:-1]), "unit": "rad"}
        for c in chans:
            m, se, n = _binned(theta, cat[c], edges)
            out[name][c] = {"mean": m, "se": se, "count": n}
    for name, x, unit in (("current", cur, "A"), ("time", tim, "s")):
        edges = np.linspace(float(x.min()), float(x.max()) + 1e-12, b + 1)
        out[name] = {"x": 0.5 * (edges[1:] + edges[:-1]), "unit": unit}
        for c in chans:
            m, se, n = _binned(x, cat[c], edges)
            out[name][c] = {"mean": m, "se": se, "count": n}
    return out


def harmonics(values: PerRecord, coords: Sequence[Coordinates], max_order: int) -> dict[str, np.ndarray]:
    """Amplitude of each mechanical harmonic 1..max_order of the rotor angle in each channel, (max_order,).

    The envelope current is demodulated first (:meth:`Coordinates.demodulated`). The signal is then averaged in 8 max_order bins of theta_m mod 2 pi (so that the dwell time at each angle
    does not weight the fit), then a cos(h theta) + b sin(h theta) + c is fitted to the occupied bins one order
    at a time. When the record covers less than a revolution, the resolution is about 2 pi / (angle travelled)
    orders and low orders mix with slow trends.
    """
    ang = np.mod(np.concatenate([k.motor_angle for k in coords]), 2 * math.pi)
    edges = np.linspace(0.0, 2 * math.pi, 8 * max_order + 1)
    centres = 0.5 * (edges[1:] + edges[:-1])
    out = {}
    for c in values[0]:
        y = np.concatenate([k.demodulated(c, v[c]) for v, k in zip(values, coords, strict=True)])
        mean, _, cnt = _binned(ang, y, edges)
        ok = cnt > 0
        th, yb = centres[ok], mean[ok]
        amps = np.zeros(max_order)
        for h in range(1, max_order + 1):
            a = np.stack([np.cos(h * th), np.sin(h * th), np.ones_like(th)], axis=1)
            coef = np.linalg.lstsq(a, yb, rcond=None)[0]
            amps[h - 1] = math.hypot(coef[0], coef[1])
        out[c] = amps
    return out


def spectrum(values: PerRecord, sample_rate: float, segment: int = 1024) -> dict[str, np.ndarray]:
    """Welch one-sided PSD of each channel (records averaged), with ``"f"`` the frequencies [Hz]."""
    out: dict[str, np.ndarray] = {}
    for c in values[0]:
        psds = []
        for v in values:
            f, p = welch(v[c], fs=sample_rate, nperseg=min(segment, len(v[c])))
            psds.append(p)
            out["f"] = f
        n = min(len(p) for p in psds)
        out[c] = np.mean([p[:n] for p in psds], axis=0)
    return out


def autocorrelation(x: np.ndarray, max_lag: int) -> np.ndarray:
    """Normalised autocorrelation rho_0..rho_max_lag (biased estimator, as in Ljung-Box)."""
    x = x - x.mean()
    d = float(x @ x)
    n = len(x)
    f = np.fft.rfft(x, 2 * n)
    ac = np.fft.irfft(f * np.conj(f))[: max_lag + 1]
    return ac / d if d > 0 else np.zeros(max_lag + 1)


def whiteness(values: PerRecord, settings: DiagnosticSettings) -> dict[str, dict]:
    """Ljung-Box test per channel over lags 1..whiteness_lags (records pooled by summing Q), plus the
    autocorrelation to max_lag and its 99 % band (+-z/sqrt(n)) for plots."""
    z = stats.norm.isf(settings.alpha / 2)
    out = {}
    for c in values[0]:
        q, n_tot, acs, lag = 0.0, 0, [], settings.whiteness_lags
        for v in values:
            x = v[c]
            n = len(x)
            rho = autocorrelation(x, max(settings.max_lag, lag))
            k = np.arange(1, lag + 1)
            q += n * (n + 2) * float(np.sum(rho[1 : lag + 1] ** 2 / (n - k)))
            n_tot += n
            acs.append(rho[: settings.max_lag + 1] * n)
        rho = np.sum(acs, axis=0) / n_tot
        dof = lag * len(values)
        p = float(stats.chi2.sf(q, dof))
        band = z / math.sqrt(n_tot)
        out[c] = {
            "q": q,
            "dof": dof,
            "p_value": p,
            "white": bool(p >= settings.alpha),
            "band": band,
            "outside_fraction": float(np.mean(np.abs(rho[1:]) > band)),
            "autocorrelation": rho,
        }
    return out


def cross_correlation(values: PerRecord, inputs: Sequence[np.ndarray], settings: DiagnosticSettings) -> dict:
    """Residual-input cross-correlation rho(k) = corr(r_t, u_{t-k}) for |k| <= max_lag per channel, its band
    +-z/sqrt(n) (valid when the residual is white) and the test n sum rho^2 ~ chi2(2 max_lag + 1)."""
    z = stats.norm.isf(settings.alpha / 2)
    lag = settings.max_lag
    out = {}
    for c in values[0]:
        acc, n_tot = np.zeros(2 * lag + 1), 0
        for v, u in zip(values, inputs):
            r = v[c] - v[c].mean()
            w = u - u.mean()
            n = len(r)
            full = np.correlate(r, w, mode="full")[n - 1 - lag : n + lag]  # lags -L..L of sum r_t w_{t-k}
            den = math.sqrt(float(r @ r) * float(w @ w))
            acc += n * (full / den if den > 0 else 0.0)
            n_tot += n
        rho = acc / n_tot
        stat = n_tot * float(np.sum(rho**2))
        p = float(stats.chi2.sf(stat, 2 * lag + 1))
        band = z / math.sqrt(n_tot)
        out[c] = {
            "lags": np.arange(-lag, lag + 1),
            "correlation": rho,
            "band": band,
            "statistic": stat,
            "p_value": p,
            "uncorrelated": bool(p >= settings.alpha),
            "outside_fraction": float(np.mean(np.abs(rho) > band)),
        }
    return out
