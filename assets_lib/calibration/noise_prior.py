"""The device's 1/f (bias-instability) level B from its long static records, as a prior for the calibration fits.

Why: the calibration fits (:func:`assets_lib.calibration.rate_fit.fit_gyro_rate`,
:func:`assets_lib.calibration.multiposition.fit_accel_multiposition`, :func:`~.multiposition.fit_gyro_static`) read B
from the run's own plateaus (segmentation's pooled Allan fit, ``<channel>_flicker_b``), which at navigation and
tactical grade cannot resolve it: the floor lies at 0.003-0.04 of a plateau's sem^2, B is detected in about half the
runs at 2-20x the truth with < 1 dof, and the bias intervals over-cover (navigation rate-fit bias z sd 0.78,
benchmarks/README.md session 9). The same fits with the device's true B give z sd 1.01-1.05. A lab has the device's
long static records; the ``allan_deviation`` stage's ``noise`` table gives per channel the [IEEE952] C.23 fit's B
with its profile interval, or only an upper bound (``is_upper_bound``) when the record does not resolve the floor.

What the fits receive per channel (:meth:`DeviceNoisePrior.flicker`), tau^2 = B^2 / pi (:func:`flicker_prior_tau2`):

* two-sided (some record resolves B): tau^2 from B and its degrees of freedom from the interval
  (:func:`flicker_dof_from_interval`, B_hat^2 ~ B^2 chi^2_nu / nu), integrated out with the plateaus' REML
  likelihood as the run's own detected B is (:func:`assets_lib.calibration.fit_core.flicker_gls`);
* an upper bound only: :class:`~assets_lib.calibration.fit_core.FlickerBoundLaw`, B <= bound: the run's own Allan
  law (:func:`~assets_lib.calibration.fit_core.flicker_law` of its plateaus, the censored likelihood) and the
  plateaus' REML likelihood, prior flat in tau, truncated at bound^2 / pi. The bound is not taken as B: it lies 2-7x
  above the truth and made the intervals wider still (session 9: z sd 0.45 navigation, 0.66 tactical on 20-min
  records).

Selection over the device's records (:meth:`DeviceNoisePrior.from_noise_tables`): per channel the two-sided
estimate with the narrowest relative interval (smallest ci_hi / ci_lo) if any record resolves B, else the smallest
upper bound. B is a property of the device (its noise spectrum), so a static record of another power cycle serves;
a device whose noise changed (ageing, a repair) needs its records filtered by the caller.

Measured on the dev cache (benchmarks/README.md, "Device noise prior" and "Session 10"): with 3 h or 8 h
records the navigation and tactical gyro biases' z sd 0.75-0.92 -> 0.95-1.04 (navigation: a bound in 596 of 600
channels at 3 h); a 20-min record's navigation bound (6.5x the truth) leaves the rate fit wide (run's B 0.75, bound
0.68: a navigation gyro needs a record of hours, [IEEE952] C.3), and a bound near the truth is still narrow (the
11 % of tactical channels a bound at 3 h: rate-fit bias z sd 1.27, 0.89 coverage; 1.62 with the bound alone).

The pipeline (``assets_lib/stages/calibration.py``) passes the prior of the device's static runs'
``allan_deviation`` outputs (sibling reads, :func:`device_noise_prior`) to the fits, bounds included.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd

from assets_lib.calibration.fit_core import (
    FlickerBoundLaw,
    flicker_dof_from_interval,
    flicker_law,
    flicker_prior_tau2,
)


@dataclass(frozen=True)
class ChannelNoisePrior:
    """One channel's B from one static record (SI: rad/s for gyros, m/s^2 for accelerometers): ``b`` NaN when
    ``is_upper_bound`` (then ``ci_hi`` is the bound), ``ci_level`` the interval's level."""

    channel: str
    b: float
    ci_lo: float
    ci_hi: float
    is_upper_bound: bool
    run_id: str
    duration_s: float
    ci_level: float = 0.95

    @property
    def bound(self) -> float:
        """The upper bound on B (``ci_hi``); meaningful for either kind."""
        return float(self.ci_hi)

    def flicker(self, run_law=None):
        """(tau2, dof or law) for :func:`fit_core.fit_linear`'s ``flicker_tau2`` / ``flicker_tau2_dof``: two-sided,
        tau^2 = B^2 / pi and nu from (hi / lo)^2 = chi^2_nu(1 - a/2) / chi^2_nu(a/2) (:func:`flicker_dof_from_interval`);
        a bound, tau2_max = bound^2 / pi with :class:`FlickerBoundLaw` (tau^2 <= tau2_max)."""
        if self.is_upper_bound:
            t2 = float(self.ci_hi) ** 2 / np.pi
            return t2, FlickerBoundLaw(t2, inner=run_law)
        return (flicker_prior_tau2(self.b),
                flicker_dof_from_interval(self.b, self.ci_lo, self.ci_hi, level=self.ci_level))

    @property
    def source(self) -> str:
        """Where B came from, for a coefficient's note."""
        if self.is_upper_bound:
            return (f"1/f level B <= {self.ci_hi:.3g} (upper bound: the run's own B integrated below it) from the "
                    f"device's static record {self.run_id} ({self.duration_s / 3600:.3g} h)")
        return (f"1/f level B = {self.b:.3g} [{self.ci_lo:.3g}, {self.ci_hi:.3g}] from the device's static record "
                f"{self.run_id} ({self.duration_s / 3600:.3g} h)")


@dataclass(frozen=True)
class DeviceNoisePrior:
    """Per channel, the device's B from its static records ([IEEE952] C.23 fit) for the fits' tau^2 = B^2 / pi
    (:class:`ChannelNoisePrior`); see the module docstring."""

    channels: tuple[ChannelNoisePrior, ...]
    device_id: str = ""

    def __post_init__(self):
        names = [c.channel for c in self.channels]
        if len(set(names)) != len(names):
            raise ValueError(f"one prior per channel, got {names}")

    def __contains__(self, channel: str) -> bool:
        return any(c.channel == channel for c in self.channels)

    def get(self, channel: str) -> ChannelNoisePrior | None:
        return next((c for c in self.channels if c.channel == channel), None)

    def flicker(self, channel: str, run_law=None):
        """(tau2, dof or law) of ``channel`` for the fits (:meth:`ChannelNoisePrior.flicker`); KeyError if absent."""
        c = self.get(channel)
        if c is None:
            raise KeyError(channel)
        return c.flicker(run_law)

    def source(self, channel: str) -> str:
        c = self.get(channel)
        return "" if c is None else c.source

    @classmethod
    def from_noise_tables(cls, noise_tables: Sequence[pd.DataFrame], run_ids: Sequence[str],
                          durations_s: Sequence[float], device_id: str = "") -> DeviceNoisePrior:
        """From the ``noise`` tables of the ``allan_deviation`` stage of the device's static runs (one per run, with
        its run id and record duration): the IEEE 952 fit rows (method "fit", parameter "B"). Per channel the
        two-sided estimate (value > 0 inside [ci_lo > 0, ci_hi], not a bound) whose interval is narrowest relative
        to itself (smallest ci_hi / ci_lo), else the smallest upper bound (``is_upper_bound`` or ci_lo <= 0: ci_hi
        is the bound); a channel with neither is left out (the fits then use the run's own B)."""
        if not (len(noise_tables) == len(run_ids) == len(durations_s)):
            raise ValueError("one run id and one duration per noise table")
        two: dict[str, tuple[float, ChannelNoisePrior]] = {}
        bnd: dict[str, ChannelNoisePrior] = {}
        for nt, run, dur in zip(noise_tables, run_ids, durations_s):
            rows = nt[(nt["method"] == "fit") & (nt["parameter"] == "B")]
            for r in rows.itertuples(index=False):
                v, lo, hi = float(r.value), float(r.ci_lo), float(r.ci_hi)
                level = float(getattr(r, "ci_level", 0.95))
                if not np.isfinite(level) or not 0 < level < 1:
                    level = 0.95
                upper = bool(r.is_upper_bound)
                if (not upper and np.isfinite(v) and v > 0 and np.isfinite(lo) and lo > 0 and np.isfinite(hi)
                        and lo <= v <= hi and hi > lo):
                    c = ChannelNoisePrior(str(r.channel), v, lo, hi, False, str(run), float(dur), level)
                    width = np.log(hi / lo)
                    if r.channel not in two or width < two[r.channel][0]:
                        two[r.channel] = (width, c)
                elif np.isfinite(hi) and hi > 0:
                    c = ChannelNoisePrior(str(r.channel), float("nan"), 0.0, hi, True, str(run), float(dur), level)
                    if r.channel not in bnd or hi < bnd[r.channel].ci_hi:
                        bnd[r.channel] = c
        chans = sorted(set(two) | set(bnd))
        return cls(tuple(two[ch][1] if ch in two else bnd[ch] for ch in chans), device_id)


def device_noise_prior(noise_tables: Sequence[pd.DataFrame], static_terms: Sequence[pd.DataFrame],
                       keys: Sequence[str] = ()) -> DeviceNoisePrior | None:
    """What the pipeline's fits get (``gyro_rate_fit``, ``accel_multiposition_fit``): the prior from the
    ``allan_deviation`` stage's ``noise`` and ``static_terms`` tables of the device's static runs (run id and record
    duration from ``static_terms``; ``keys`` name the runs whose ``static_terms`` is empty), per channel a two-sided
    B or, where no record resolves it, the bound (module docstring); None without a static run."""
    if not noise_tables:
        return None
    keys = list(keys) or [f"static run {i}" for i in range(len(noise_tables))]
    run_ids = [str(t["run_id"].iloc[0]) if len(t) else k for t, k in zip(static_terms, keys)]
    durations = [float(t["duration_s"].iloc[0]) if len(t) else float("nan") for t in static_terms]
    return DeviceNoisePrior.from_noise_tables(list(noise_tables), run_ids, durations)


def prior_flicker(noise_prior: DeviceNoisePrior | None, channel: str, plateaus=None):
    """(flicker_tau2, flicker_tau2_dof, source) of ``channel`` from the device's prior for a fit, or None without a
    prior or without the channel (the fit then reads the run's own B, as before). ``plateaus``: the run's plateau
    table; a bound then truncates the run's own Allan law (:func:`flicker_law`) instead of replacing it."""
    if noise_prior is None or channel not in noise_prior:
        return None
    run_law = flicker_law(plateaus, channel) if plateaus is not None else None
    t2, dof = noise_prior.flicker(channel, run_law)
    return t2, dof, noise_prior.source(channel)


def with_source(note: str, source: str) -> str:
    """A coefficient's note with where B came from appended (unchanged when ``source`` is '': the run's own B)."""
    if not source:
        return note
    return f"{note}; {source}" if note else source
