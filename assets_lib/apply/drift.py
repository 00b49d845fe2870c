"""Bias drift between the calibration and the data it is applied to, from the calibration's Allan noise terms.

A calibration fixes a triad's bias as it was over the calibration run; data taken at another time see the bias
wander by the device's bias instability (flicker, [IEEE952] C.3 term B) and rate/acceleration random walk
([IEEE952] term K). This wander is not a coefficient error, so the coefficients' standard errors do not hold it,
and it must be added to the uncertainty of the corrected data ([GUM] eq. 10, an independent input).

Model, for data averaged over windows of length T inside a run of length L (T <= L), at elapsed time t since
the run's start (the project's flicker convention, the same as the fits' bias uncertainty,
``assets_lib.calibration.fit_core.flicker_gls``: a run's mean wanders from the device's long-term bias by the
Allan floor at the run length, sigma_A^2(L) = (2 ln2 / pi) B^2):

    var_flicker(T, L) = (B^2 / pi) (2 ln2 + ln(L / T))      the Allan floor at L plus the 1/f growth from L down
                                                            to T ([IEEE952] C.3: one-sided PSD B^2 / (pi f));
    var_rw(t, T)      = K^2 (t + T / 3)                     random walk since the run's start (turn-on), window
                                                            mean of a Wiener process ([IEEE952] C.4);
    var_turn_on       = B_r^2                               only when the data come from another power cycle
                                                            than the calibration ([SEED000] eq. 23: turn-on to
                                                            turn-on bias repeatability).

Measured on the simulator's flicker (1,500 draws each): var of a 5 s window in a 300 s run 1.79 B^2 (model
1.74), 30 s window 1.28 (1.17), the whole run 0.444 (0.441), 5 s in 2,000 s 2.48 (2.35).

Only Allan terms the static run IDENTIFIED enter (``method`` 'fit', not an upper bound): a term the curve could
not resolve is reported as a one-sided bound, and taking the bound as a value over-states the drift by the
bound's slack (an accelerometer K bound from a 20 min static run is worth ~20 ug over 150 s while the simulated
device has none); such terms are named in ``BiasDrift.not_included`` so a reader sees what was left out. A
calibration without noise terms (no static run) has no drift term at all and says so (``BiasDrift.note``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

AXES = ("x", "y", "z")
CHANNELS = {"gyro": tuple(f"gyro_{a}_radps" for a in AXES), "accel": tuple(f"accel_{a}_mps2" for a in AXES)}
LN2x2 = 2.0 * math.log(2.0)


@dataclass(frozen=True)
class ApplySpan:
    """The time structure of the data a calibration is applied to: each row is a mean over ``window_s`` (one
    sample: 1 / sample rate; a plateau mean: the plateau length) at ``elapsed_s`` (window start) since the start
    of a run of ``run_s``; ``power_cycle_changed`` when the data come from another turn-on than the calibration."""

    window_s: float | np.ndarray
    run_s: float
    elapsed_s: float | np.ndarray = 0.0
    power_cycle_changed: bool = False

    def arrays(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        T = np.broadcast_to(np.asarray(self.window_s, dtype=float), (n,)).copy()
        t = np.broadcast_to(np.asarray(self.elapsed_s, dtype=float), (n,)).copy()
        if not (np.isfinite(self.run_s) and self.run_s > 0):
            raise ValueError(f"ApplySpan.run_s: expected a positive run length in s, got {self.run_s!r}")
        if np.any(~np.isfinite(T)) or np.any(T <= 0):
            raise ValueError("ApplySpan.window_s: expected positive window lengths in s")
        return np.minimum(T, self.run_s), np.maximum(t, 0.0)


@dataclass(frozen=True)
class TriadDrift:
    """Identified drift terms of one triad, SI (per axis; 0 where not identified)."""

    b: np.ndarray  # bias instability B: rad/s or m/s^2
    k: np.ndarray  # random walk K: rad/s/sqrt(s) or m/s^2/sqrt(s)
    turn_on: np.ndarray  # turn-on bias repeatability B_r (NaN: unknown)


@dataclass(frozen=True)
class BiasDrift:
    """Drift terms of both triads, where they came from and what was left out."""

    gyro: TriadDrift
    accel: TriadDrift
    source: str  # run id of the noise record, '' when none
    not_included: tuple[str, ...] = field(default=())  # 'accel_x_mps2 K (upper bound 1.7e-05 m/s^2/sqrt(s))'
    note: str = ""

    def variance(self, sensor: str, span: ApplySpan | None, n: int) -> np.ndarray:
        """(n, 3) bias-drift variance of each row and axis (module docstring); ``span`` None: every row the mean of
        a whole run, the Allan floor (2 ln2 / pi) B^2 only."""
        d: TriadDrift = getattr(self, sensor)
        if span is None:
            return np.broadcast_to((LN2x2 / math.pi) * d.b**2, (n, 3)).copy()
        T, t = span.arrays(n)
        flick = (d.b**2 / math.pi)[None, :] * (LN2x2 + np.log(span.run_s / T))[:, None]
        rw = (d.k**2)[None, :] * (t + T / 3.0)[:, None]
        var = flick + rw
        if span.power_cycle_changed:
            if np.any(~np.isfinite(d.turn_on)):
                raise ValueError(f"{sensor}: the data come from another power cycle than the calibration, but the "
                                 "turn-on bias repeatability is unknown (it needs records of several power cycles)")
            var = var + (d.turn_on**2)[None, :]
        return var


def bias_drift(noise_rows, source: str = "", turn_on: dict | None = None) -> BiasDrift:
    """The drift terms held by a calibration's noise rows (``noise_table`` layout: channel, parameter, method,
    value, ci_hi, is_upper_bound; SI values) and its turn-on repeatability (``{"gyro": [3], "accel": [3]}`` SI,
    ``assets_lib.apply.model.turn_on_repeatability``; missing: unknown)."""
    rows = list(noise_rows or ())
    rep = {s: np.asarray((turn_on or {}).get(s, [np.nan] * 3), dtype=float) for s in CHANNELS}
    if not rows:
        return BiasDrift(TriadDrift(np.zeros(3), np.zeros(3), rep["gyro"]),
                         TriadDrift(np.zeros(3), np.zeros(3), rep["accel"]), "", (),
                         "no noise terms (static run) in the calibration: bias drift between runs not included in "
                         "the stated uncertainty")
    out = {"gyro": {"B": np.zeros(3), "K": np.zeros(3)}, "accel": {"B": np.zeros(3), "K": np.zeros(3)}}
    left = []
    for r in rows:
        if r.get("method") != "fit" or r.get("parameter") not in ("B", "K"):
            continue
        for sensor, chans in CHANNELS.items():
            if r.get("channel") in chans:
                i = chans.index(r["channel"])
                v = r.get("value")
                if r.get("is_upper_bound") or v is None or not math.isfinite(float(v)):
                    hi = r.get("ci_hi")
                    bound = f"{float(hi):.3g}" if hi is not None else "n/a"
                    left.append(f"{r['channel']} {r['parameter']} (upper bound {bound} {r.get('unit', '')}".rstrip()
                                + ")")
                else:
                    out[sensor][r["parameter"]][i] = float(v)
    mk = lambda s: TriadDrift(out[s]["B"], out[s]["K"], rep[s])
    note = ("bias drift between runs from the noise terms of " + (source or "the calibration")
            + (("; not identified, left out: " + ", ".join(left)) if left else ""))
    return BiasDrift(mk("gyro"), mk("accel"), source, tuple(left), note)


__all__ = ["ApplySpan", "BiasDrift", "TriadDrift", "bias_drift"]
