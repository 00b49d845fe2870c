"""Effect library: signature regressors of every testable twin family, and their injection into the twin.

simreal.md sec. 4.1 (effect dictionary) with the physics of effects.md sec. 1. Each family is linear in its
coefficients, with at most one profiled shape parameter (the warm-up time constant). ``columns(block, feat,
channel, shape)`` returns the signature columns on a block's rows (``None`` when the family has no signature
there); ``inject`` adds the same physics to twin outputs (the augmented twin); ``magnitude`` turns coefficients
into the family's canonical SI magnitude.

Blocks (``design.py``): ``A`` plateau means (one row per plateau and channel), ``B`` table-angle-resolved
residuals inside rate windows (10 Hz block means, window mean removed), ``C`` one row per run: the clock drift
measured by segmentation's table/IMU alignment, ``D`` run level (``run_level.py``): each run's fitted bias with
the power cycle's bias as nuisance; a family's block-D signature is its block-A signature through the same
bias estimator, so only ``extra_blocks=("D",)`` marks it (bias ramp, warm-up, temperature bias: the families
that move the bias between the runs of a power cycle; their folds are power cycles).

Families and their folds (issue 12: folds are the runs that carry the signature):

=========================== ====== ==================================================== =========================
family                      block  signature (channel j)                                folds
=========================== ====== ==================================================== =========================
temperature_bias            A, D   T_lag - T0 (T lagged by 0..400 s, profiled)          power cycles
temperature_scale_factor    A      x_j (T_lag - T0), x = omega (gyro) or f (accel)      runs
warmup_bias                 A, D   exp(-t_on / tau), tau profiled in 120..2400 s        power cycles
bias_ramp                   A, D   t_on (time since power-on)                           power cycles
g_sensitivity               A      f_x^2, f_y^2, f_z^2 (g-squared part; linear G is     runs
                                   in the base model)
scale_factor_nonlinearity   A      omega_j^2, omega_j^3                                 rate runs
scale_factor_asymmetry      A      |omega_j|                                            rate runs
lever_arm                   A      omega x (omega x r) on the accelerometers (3 cols)   rate runs
table_rate_error            B      u_j omega_t {sin, cos}(k theta), k = 1, 2            rate runs
table_wobble                B, A   accelerometers: -(e_m x f)_j, m = 1, 2 (1/rev); gyros:    runs
                                   none (a rigid axis tilt leaves the body rate unchanged);
                                   on A its plateau means (partial revolutions, static
                                   poses: the tilted base tilts every pose)
timebase_error              C      clock drift [ppm] = -1e6 eps (t_imu = (1+eps) t)     runs with a table log
=========================== ====== ==================================================== =========================

Not in the deterministic library (reported ``not_testable`` with the reason): ``latency`` (a common IMU latency
is the table/IMU clock offset that segmentation estimates and removes), ``bias_step`` (a one-off step within
one run has no second run to validate it), ``vibration`` (spectral-peak view only), ``noise_model`` (stochastic
views; verdict ``noise_model``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

T0_DEGC = 25.0
WARMUP_TAUS_S = (120.0, 300.0, 900.0, 2400.0)
#: thermal lag between the sensor die and the logged thermometer (first-order), profiled like the warm-up tau
THERMAL_LAGS_S = (0.0, 60.0, 150.0, 400.0)
GYRO = (0, 1, 2)
ACCEL = (3, 4, 5)
CHANNEL_NAMES = ("gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z")

NOT_TESTABLE = {
    "latency": "a common IMU latency equals the table/IMU clock offset that segmentation estimates by "
               "cross-correlation, so it leaves no residual (effects.md sec. 2: latency <-> clock offset)",
    "bias_step": "a one-off step in one run cannot be validated on another run (leave-one-run-out); it shows in "
                 "the plateau-residual views",
    "vibration": "localised by the residual-spectrum views only (no deterministic candidate)",
    "noise_model": "stochastic: routed to the noise-model verdict by the Allan-band views",
}


@dataclass(frozen=True)
class Family:
    name: str
    unit: str
    channels: tuple  # channel indices it can act on; () = joint over channels (channel null)
    block: str
    n_coef: int
    shapes: tuple = (None,)
    rate_runs_only: bool = False
    #: further blocks with signature columns (the wobble: its plateau means on block A as well as block B; "D":
    #: the run-level bias block, whose columns come from the block-A ones, ``run_level.py``)
    extra_blocks: tuple = ()


FAMILIES: dict[str, Family] = {f.name: f for f in (
    Family("temperature_bias", "rad/s/K | m/s^2/K", GYRO + ACCEL, "A", 1, THERMAL_LAGS_S, extra_blocks=("D",)),
    Family("temperature_scale_factor", "1/K", GYRO + ACCEL, "A", 1, THERMAL_LAGS_S),
    Family("warmup_bias", "rad/s | m/s^2", GYRO + ACCEL, "A", 1, WARMUP_TAUS_S, extra_blocks=("D",)),
    Family("bias_ramp", "rad/s^2 | m/s^3", GYRO + ACCEL, "A", 1, extra_blocks=("D",)),
    Family("g_sensitivity", "rad/s per (m/s^2)^2", GYRO, "A", 3),
    Family("scale_factor_nonlinearity", "1", GYRO, "A", 2, rate_runs_only=True),
    Family("scale_factor_asymmetry", "1", GYRO, "A", 1, rate_runs_only=True),
    Family("lever_arm", "m", (), "A", 3, rate_runs_only=True),
    Family("table_rate_error", "1", (), "B", 4, rate_runs_only=True),
    Family("table_wobble", "rad", (), "B", 2, extra_blocks=("A",)),
    Family("timebase_error", "1", (), "C", 1),
)}


def unit_of(family: str, channel: int | None) -> str:
    u = FAMILIES[family].unit
    if "|" in u:
        return u.split(" | ")[0 if (channel is None or channel < 3) else 1]
    return u


def has_block(family: str, block: str) -> bool:
    """Does ``family`` have signature columns on ``block``?"""
    f = FAMILIES[family]
    return block == f.block or block in f.extra_blocks


def columns(family: str, block: str, feat: dict, channel: int, shape=None) -> np.ndarray | None:
    """Signature columns (rows of ``feat`` x n_coef) on rows of output channel ``channel`` of ``block``."""
    fam = FAMILIES[family]
    if not has_block(family, block):
        return None
    n = feat["n"]
    z = np.zeros((n, fam.n_coef))
    j = channel
    if block == "A":
        w, f, T, ton = feat["omega"], feat["force"], feat["temp"], feat["t_on"]
        if family.startswith("temperature") and shape and "temp_lag" in feat:
            T = feat["temp_lag"][float(shape)]
        rate = feat["is_rate"]
        if family == "temperature_bias":
            z[:, 0] = T - T0_DEGC
        elif family == "temperature_scale_factor":
            x = w[:, j] if j < 3 else f[:, j - 3]
            z[:, 0] = x * (T - T0_DEGC)
        elif family == "warmup_bias":
            z[:, 0] = np.exp(-ton / float(shape))
        elif family == "bias_ramp":
            z[:, 0] = ton
        elif family == "g_sensitivity":
            if j >= 3:
                return None
            z[:] = f**2
        elif family == "scale_factor_nonlinearity":
            if j >= 3:
                return None
            z[:, 0] = np.where(rate, w[:, j] ** 2, 0.0)
            z[:, 1] = np.where(rate, w[:, j] ** 3, 0.0)
        elif family == "scale_factor_asymmetry":
            if j >= 3:
                return None
            z[:, 0] = np.where(rate, np.abs(w[:, j]), 0.0)
        elif family == "lever_arm":
            if j < 3:
                return None
            wm = feat["omega_motion"]
            a = j - 3
            for k in range(3):
                z[:, k] = np.where(rate, wm[:, a] * wm[:, k] - (a == k) * np.sum(wm**2, axis=1), 0.0)
        elif family == "table_wobble":
            # the same rigid tilt on the plateau means: -(e_m x f) averaged over each plateau's samples
            # (``design.block_a_features``: "wobble", (n, 2, 3)). Over whole revolutions the 1/rev term averages
            # out, over the partial revolutions of slow or short plateaus it does not, and in static poses it is a
            # constant level-frame tilt of gravity seen in each pose's body axes; block B (window means removed)
            # misses all of it (measured on WH-019: the plateau-mean residual was taken by a bias ramp)
            if j < 3 or "wobble" not in feat:
                return None
            z[:] = feat["wobble"][:, :, j - 3]
    elif block == "B":
        th, wt, u, e1, e2, f = feat["theta"], feat["rate_t"], feat["u"], feat["e1"], feat["e2"], feat["force"]
        if family == "table_rate_error":
            if j >= 3:
                return None
            for k, h in enumerate((1, 2)):
                z[:, 2 * k] = u[:, j] * wt * np.sin(h * th)
                z[:, 2 * k + 1] = u[:, j] * wt * np.cos(h * th)
        elif family == "table_wobble":
            # a rigid tilt eps of the bearing axis (fixed in the level frame): the table spins about a body-fixed
            # axis, so the body rate is unchanged (no gyro term; the earth-rate projection moves by
            # Omega_e eps ~ 1e-8 rad/s, negligible) while the tilt, seen from the IMU, turns once per revolution
            # and rotates the specific force: delta f_b = -(eps_b x f_b) (effects.md sec. 1, table wobble;
            # assets_lib.sim.effects.motion.TableWobble)
            if j < 3:
                return None
            for m, e in enumerate((e1, e2)):
                z[:, m] = -np.cross(e, f)[:, j - 3]
    elif block == "C" and family == "timebase_error":
        # segmentation's clock drift of a run whose IMU stamps run fast, t_imu = (1 + eps) t_table, is -1e6 eps
        z[:, 0] = -1e6
    return z


def magnitude(family: str, coef: np.ndarray, scale: dict, channel: int | None = None) -> float:
    """Canonical magnitude of fitted coefficients (SI; see the family table)."""
    c = np.atleast_1d(np.asarray(coef, float))
    if family == "scale_factor_nonlinearity":
        wmax = scale.get("omega_max", 1.0)  # max deviation over full scale, relative to full scale
        ws = np.linspace(-wmax, wmax, 201)
        return float(np.max(np.abs(c[0] * ws**2 + c[1] * ws**3)) / wmax) * float(np.sign(c[0] + c[1] * wmax or 1.0))
    if family == "scale_factor_asymmetry":
        return float(2.0 * c[0])  # K+ - K- relative: |omega| coefficient = eps_a / 2
    if family in ("lever_arm", "table_wobble"):
        return float(np.linalg.norm(c))
    if family == "table_rate_error":
        return float(max(np.hypot(c[0], c[1]), np.hypot(c[2], c[3])))
    if family == "g_sensitivity":
        # f_x^2 + f_y^2 + f_z^2 = g^2 in static positions: only differences of the three coefficients are identifiable
        # (a common part is a bias); the magnitude is the own-axis coefficient over the mean of the other two
        j = 0 if channel is None else channel % 3
        return float(c[j] - np.mean(np.delete(c[:3], j)))
    return float(c[0])


def lagged_temperature(t_s: np.ndarray, temp_degc: np.ndarray, lag_s: float) -> np.ndarray:
    """First-order lag of the logged temperature (die vs thermometer): dT_die/dt = (T - T_die) / lag."""
    if not lag_s:
        return temp_degc
    from scipy.signal import lfilter

    dt = float(np.median(np.diff(t_s)))
    a = np.exp(-dt / lag_s)
    return lfilter([1 - a], [1, -a], temp_degc - temp_degc[0]) + temp_degc[0]


def inject(family: str, channel, coef, shape, inp, g: np.ndarray, a: np.ndarray, rng=None):
    """Add an effect in the library's form to twin outputs (SI) of one run with recorded inputs ``inp``."""
    c = np.atleast_1d(np.asarray(coef, float))
    j = None if channel is None else CHANNEL_NAMES.index(channel)
    T = lagged_temperature(inp.t_s, inp.temperature_degc, float(shape or 0.0)) if family.startswith("temperature") \
        else inp.temperature_degc
    w, f = inp.omega_b_radps, inp.f_b_mps2
    out = [g.copy(), a.copy()]

    def add(jj, v):
        out[0 if jj < 3 else 1][:, jj % 3] += v

    if family == "temperature_bias":
        add(j, c[0] * (T - T0_DEGC))
    elif family == "temperature_scale_factor":
        x = w[:, j] if j < 3 else f[:, j - 3]
        add(j, c[0] * x * (T - T0_DEGC))
    elif family == "warmup_bias":
        add(j, c[0] * np.exp(-inp.t_on_s / float(shape)))
    elif family == "bias_ramp":
        add(j, c[0] * inp.t_on_s)
    elif family == "g_sensitivity":
        add(j, f**2 @ c[:3])
    elif family == "scale_factor_nonlinearity":
        add(j, c[0] * w[:, j] ** 2 + c[1] * w[:, j] ** 3)
    elif family == "scale_factor_asymmetry":
        add(j, c[0] * np.abs(w[:, j]))
    elif family == "lever_arm":
        wm = inp.table_rate_radps[:, None] * inp.table_axis_b
        r = c[:3]
        acc = wm * (wm @ r)[:, None] - np.sum(wm**2, axis=1)[:, None] * r
        dt = np.gradient(inp.t_s)
        alpha = np.gradient(inp.table_rate_radps) / dt
        acc = acc + np.cross(alpha[:, None] * inp.table_axis_b, r)
        out[1] += acc
    elif family == "table_rate_error":
        th, wt = inp.table_angle_rad, inp.table_rate_radps
        rip = c[0] * np.sin(th) + c[1] * np.cos(th) + c[2] * np.sin(2 * th) + c[3] * np.cos(2 * th)
        out[0] += (wt * rip)[:, None] * inp.table_axis_b
    elif family == "table_wobble":
        eps = c[0] * inp.tilt_e1_b + c[1] * inp.tilt_e2_b  # rigid axis tilt: accelerometers only (columns)
        out[1] += -np.cross(eps, f)
    elif family == "timebase_error":
        pass  # acts on the time stamps (twin.simulate_run_imu)
    return out[0], out[1]
