"""Effect families of the digital twin: one registry, one signature per stage, parameters in SI.

Every family is a frozen dataclass whose fields are its parameters, in SI with the unit in the name
(``gyro_radps_per_k``, ``delay_s``, ``position_m``); vectors are per-axis tuples (x, y, z) in body axes.
``EFFECTS`` maps the family name (the name the sim-to-real diagnosis reports) to the class, as pvlib's
``iam.py`` maps model names to functions:

    >>> from assets_lib.sim.effects import EFFECTS, effect_from_dict
    >>> eff = EFFECTS["temperature_bias"](gyro_radps_per_k=(1e-5, 0, 0))
    >>> effect_from_dict(eff.to_dict()) == eff
    True

Serialised form (``to_dict``/``from_dict``, used by device-model files and ``_truth/``):
``{"family": "<name>", "params": {<field>: <value>, ...}}``; lists stand for tuples.

Stages (``Effect.stage``) and the one hook each stage calls, in the order the simulator runs them
(:func:`assets_lib.sim.simulator.simulate_run`):

1. ``"clock"`` (latency, timebase_error): ``true_time_s(t_s, triad) -> t`` maps the IMU sample times of the
   ``triad`` ('gyro' | 'accel') to the true (table) times at which that triad senses its input;
   ``input_gain(triad) -> float`` multiplies the sensed input (1 unless the outputs integrate over a sample
   period timed by a wrong clock).
2. ``"table"`` (table_rate_error, table_wobble): ``perturb(motion: TableMotion) -> TableMotion`` changes the true
   table motion (orientation C_b^l, level-frame motion rate, table angle and rate) while the written table log
   keeps the nominal (commanded) motion.
3. ``"input"`` (lever_arm, vibration): ``add_inputs(inputs: BodyInputs, motion: TableMotion) -> BodyInputs``
   adds to the true body rate / specific force that the triad senses.
4. ``"sensor"`` (temperature_bias, temperature_scale_factor, warmup_bias, bias_ramp, bias_step, g_sensitivity,
   scale_factor_nonlinearity, scale_factor_asymmetry) and ``"noise"`` (noise_model):
   ``apply(ctx, gyro, accel) -> (gyro, accel)`` on the (n, 3) SI outputs, the ``SensorEffect`` protocol of the
   simulator. :func:`sensor_chain` puts sensor effects after the deterministic error model and noise effects
   after the Allan noise, before saturation.

What ``ctx`` (``simulator.SimContext``) offers a sensor-stage effect: ``t_s`` (IMU clock, s from the run's
first sample), ``time_since_power_on_s``, ``temperature_degc`` (thermometer temperature, noise-free in a
simulation, the recorded log in a replay), ``inputs`` (gyro triad's ``BodyInputs``: ``omega_b_radps``,
``f_b_mps2``), ``accel_inputs`` (accelerometer triad's), ``truth`` (``DeviceTruth``), ``rng`` (seeded),
``step_index``, ``rate_hz``.

A new family: one frozen dataclass with ``family`` and ``stage`` class attributes and its stage's hook,
registered with ``@register``; nothing else changes. No family is on by default: the default chain
``simulator.DEFAULT_EFFECTS`` is the base model, so the default archive is unchanged byte for byte.
"""

from __future__ import annotations

from assets_lib.sim.effects import clock, motion, response, stochastic, thermal  # noqa: F401  (registration)
from assets_lib.sim.effects.base import (
    EFFECTS,
    Effect,
    TableMotion,
    effect_from_dict,
    effects_from_list,
    register,
    sensor_chain,
    split_stages,
)

__all__ = ["EFFECTS", "Effect", "TableMotion", "effect_from_dict", "effects_from_list", "register", "sensor_chain",
           "split_stages"]
