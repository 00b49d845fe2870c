"""Contracts of the tables imulab derives (plateaus, coefficients, residuals, Allan, noise), as Arrow schemas.

The pipeline's blocking schema checks are generated from these (``pipelines/checks.py``); columns listed here
must be present with these types; stages may add further columns.
"""

from __future__ import annotations

import pyarrow as pa

F, I, S, B = pa.float64(), pa.int64(), pa.string(), pa.bool_()
CHANNELS = ("gyro_x_radps", "gyro_y_radps", "gyro_z_radps", "accel_x_mps2", "accel_y_mps2", "accel_z_mps2")


def _f(name, typ, unit=None, doc=None):
    md = {}
    if unit:
        md["unit"] = unit
    if doc:
        md["doc"] = doc
    return pa.field(name, typ, metadata=md or None)


PLATEAU_SCHEMA = pa.schema(
    [
        _f("device_id", S), _f("run_id", S), _f("step_index", I), _f("kind", S, doc="rate | static"),
        _f("t_start_s", F, "s"), _f("t_end_s", F, "s"), _f("n_samples", I), _f("n_rejected", I),
        _f("rejected_fraction", F), _f("commanded_rate_radps", F, "rad/s"), _f("revolutions", F),
        *[_f(f"{c}_{s}", F, c.rsplit("_", 1)[1]) for c in CHANNELS for s in ("mean", "sem")],
        _f("temperature_degc_mean", F, "degC"),
        *[_f(f"omega_ref_{a}_radps", F, "rad/s") for a in "xyz"],
        *[_f(f"omega_earth_{a}_radps", F, "rad/s") for a in "xyz"],
        *[_f(f"f_ref_{a}_mps2", F, "m/s^2") for a in "xyz"],
        _f("flagged", B), _f("flag_reason", S),
    ]
)

COEFFICIENT_SCHEMA = pa.schema(
    [
        _f("device_id", S), _f("run_id", S), _f("sensor", S, doc="gyro | accel"), _f("axis", S, doc="x | y | z"),
        _f("coefficient", S), _f("value", F), _f("stderr", F), _f("unit", S, doc="SI unit of value"),
        _f("value_lab", F), _f("stderr_lab", F), _f("unit_lab", S), _f("observable", B),
        _f("n_plateaus", I), _f("n_samples", I), _f("method", S),
    ]
)

ALLAN_SCHEMA = pa.schema(
    [_f("channel", S), _f("tau_s", F, "s"), _f("adev", F), _f("ci_lo", F), _f("ci_hi", F), _f("edf", F), _f("n_terms", I)]
)

NOISE_SCHEMA = pa.schema(
    [
        _f("channel", S), _f("parameter", S), _f("value", F), _f("ci_lo", F), _f("ci_hi", F), _f("unit", S),
        _f("value_lab", F), _f("ci_lo_lab", F), _f("ci_hi_lab", F), _f("unit_lab", S), _f("method", S),
        _f("is_upper_bound", B),
    ]
)


def type_family(t: pa.DataType) -> str:
    """Coarse family used for conformance: float, int, string, bool, other."""
    if pa.types.is_floating(t):
        return "float"
    if pa.types.is_integer(t):
        return "int"
    if pa.types.is_string(t) or pa.types.is_large_string(t):
        return "string"
    if pa.types.is_boolean(t):
        return "bool"
    if pa.types.is_null(t):
        return "null"
    return str(t)


def conformance_problems(got: pa.Schema, contract: pa.Schema, exact: bool = False) -> list[str]:
    """What keeps a table with schema ``got`` from meeting ``contract`` (missing columns, wrong type family)."""
    problems = []
    if exact and got.names != contract.names:
        problems.append(f"columns {got.names} != {contract.names}")
    for f in contract:
        if f.name not in got.names:
            problems.append(f"missing column {f.name!r}")
            continue
        fam, want = type_family(got.field(f.name).type), type_family(f.type)
        ok = fam == want or (want == "float" and fam == "int") or fam == "null"
        if exact:
            ok = got.field(f.name).type.equals(f.type)
        if not ok:
            problems.append(f"column {f.name!r} has type {got.field(f.name).type}, expected {f.type}")
    return problems
