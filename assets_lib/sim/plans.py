"""Standard test plans, kept as data in ``plan_library/*.json``, expanded into timed ``raw_schemas.TestPlan`` s.

A template step names the mount by where each body axis points (``{"x": "N", "y": "W", "z": "U"}``), optional
body rotations (``[["x", 45.0]]``), the table rate, and a duration (or a number of whole ``revolutions``,
[SEED000]'s full-revolution method). Expansion lays the steps on a time line with ``transition_s`` between
them and fills the step-start orientations from the kinematics (``kinematics.consistent_plan_orientations``).
"""

from __future__ import annotations

import json
from importlib import resources

import numpy as np

from assets_lib.sim.kinematics import consistent_plan_orientations, rotation_about
from raw_schemas.manifest import TestPlan

_LEVEL_AXES = {
    "ENU": {"E": (1, 0, 0), "W": (-1, 0, 0), "N": (0, 1, 0), "S": (0, -1, 0), "U": (0, 0, 1), "D": (0, 0, -1)},
    "NED": {"N": (1, 0, 0), "S": (-1, 0, 0), "E": (0, 1, 0), "W": (0, -1, 0), "D": (0, 0, 1), "U": (0, 0, -1)},
}
_BODY = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}


def available_plans() -> list[str]:
    """Names of the plans in the library."""
    files = resources.files("assets_lib.sim").joinpath("plan_library").iterdir()
    return sorted(f.name[:-5] for f in files if f.name.endswith(".json"))


def load_template(name: str) -> dict:
    """The raw JSON template of a library plan."""
    path = resources.files("assets_lib.sim").joinpath("plan_library", f"{name}.json")
    if not path.is_file():
        raise KeyError(f"unknown plan {name!r}; available: {available_plans()}")
    return json.loads(path.read_text())


def mount_dcm(axes: dict[str, str], rotate_body=(), frame: str = "ENU") -> np.ndarray:
    """C_b^l whose columns are the level-frame directions of the body axes, then body-fixed rotations applied."""
    lv = _LEVEL_AXES[frame]
    c = np.column_stack([lv[axes[a]] for a in ("x", "y", "z")]).astype(float)
    if abs(np.linalg.det(c) - 1.0) > 1e-9:
        raise ValueError(f"axes {axes} do not form a right-handed frame")
    for ax, deg in rotate_body:
        c = c @ rotation_about(_BODY[ax], np.radians(deg))
    return c


def build_plan(template: dict | str, duration_scale: float = 1.0, static_duration_s: float | None = None) -> TestPlan:
    """Expand a template into a timed plan. ``duration_scale`` shortens dwell times (not whole revolutions)."""
    tpl = load_template(template) if isinstance(template, str) else template
    frame = tpl.get("frame", "ENU")
    t = float(tpl.get("lead_s", 0.0))
    gap = float(tpl.get("transition_s", 0.0))
    steps = []
    for i, s in enumerate(tpl["steps"]):
        settle = float(s.get("settle_s", 0.0))
        rate = float(s.get("table_rate_dps", 0.0))
        if "revolutions" in s and rate != 0.0:
            dur = settle + float(s["revolutions"]) * 360.0 / abs(rate)
        elif s["kind"] == "static" and static_duration_s is not None:
            dur = float(static_duration_s)
        else:
            dur = float(s["duration_s"]) * duration_scale
        settle = min(settle, 0.5 * dur)
        steps.append(
            {
                "index": i,
                "kind": s["kind"],
                "start_s": round(t, 9),
                "duration_s": dur,
                "settle_s": settle,
                "table_rate_dps": rate,
                "label": s.get("label", _label(s)),
                "mount_b2l": mount_dcm(s["axes"], s.get("rotate_body", ()), frame),
            }
        )
        t += dur + gap
    axis = tuple(tpl.get("table_axis_level", (0.0, 0.0, 1.0)))
    steps = consistent_plan_orientations(steps, axis)
    return TestPlan(name=tpl["name"], frame=frame, table_axis_level=axis, steps=steps)


def _label(s: dict) -> str:
    up = [a for a, d in s["axes"].items() if d == "U"]
    rot = "".join(f" rot{a}{d:+g}" for a, d in s.get("rotate_body", ()))
    if s["kind"] == "rate":
        return f"{up[0] if up else '?'}-up {s.get('table_rate_dps', 0.0):+g} deg/s"
    return f"{up[0] if up else '?'}-up{rot}"
