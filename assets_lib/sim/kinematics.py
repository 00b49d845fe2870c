"""Turntable kinematics of a test plan: body orientation, angular rate and specific force at any time.

A rate step turns the IMU about the table axis: C_b^l(t) = R(a, r (t - t_k)) C_k ([SEED000] eq. 3-5).
Between steps with the same mount the table rate ramps linearly; a change of mount (multi-position tests,
a new rate axis) is made as ramp-down, a smooth rotation (raised-cosine angle profile), ramp-up, one third
of the gap each. ``consistent_plan_orientations`` builds the step-start orientations that make a plan
follow exactly these kinematics (what the simulator writes into its manifests).
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from contextlib import contextmanager
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial.transform import Rotation

from assets_lib.sim.earth import earth_rate_level, specific_force_level

_SAME_MOUNT_TOL_RAD = 1e-6
#: deceleration of the table after the last step [rad/s^2]
TAIL_DECEL_RADPS2 = np.radians(200.0)


def rotation_about(axis: np.ndarray, angle_rad: np.ndarray | float) -> np.ndarray:
    """Rodrigues' formula: DCM(s) of a right-handed rotation by ``angle_rad`` about unit ``axis`` -> (..., 3, 3)."""
    u = np.asarray(axis, dtype=float)
    th = np.asarray(angle_rad, dtype=float)[..., None, None]
    ux = np.array([[0, -u[2], u[1]], [u[2], 0, -u[0]], [-u[1], u[0], 0]])
    return np.cos(th) * np.eye(3) + (1 - np.cos(th)) * np.outer(u, u) + np.sin(th) * ux


def _about_axis_angle(delta: np.ndarray, axis: np.ndarray) -> float | None:
    """Angle of ``delta`` if it is a rotation about ``axis`` (else None)."""
    rv = Rotation.from_matrix(delta).as_rotvec()
    ang = np.linalg.norm(rv)
    if ang < _SAME_MOUNT_TOL_RAD:
        return 0.0
    if np.linalg.norm(np.cross(rv / ang, axis)) < 1e-6:
        return float(np.dot(rv, axis))
    return None


@dataclass(frozen=True)
class Trajectory:
    """Sampled table motion: C_b^l (n,3,3), level-frame motion rate (n,3) [rad/s], table angle/rate, step index."""

    t_s: np.ndarray
    c_b2l: np.ndarray
    omega_motion_level_radps: np.ndarray
    table_angle_rad: np.ndarray
    table_rate_radps: np.ndarray
    step_index: np.ndarray


def _wrap_equal(a: float, b: float) -> bool:
    return abs((a - b + np.pi) % (2 * np.pi) - np.pi) < 1e-6


def _sub(outer, inner):
    """Intersection of two selections from ``between`` (both slices or both masks)."""
    if isinstance(outer, slice):
        return slice(max(outer.start, inner.start), max(min(outer.stop, inner.stop), max(outer.start, inner.start)))
    return outer & inner


def _compute_trajectory(plan, t_s: np.ndarray) -> Trajectory:
    """Evaluate the plan's kinematics at times ``t_s`` (see :func:`trajectory`). Every output element depends on
    its own time only (no reductions), so a sample's value does not depend on which other samples are asked for."""
    t = np.asarray(t_s, dtype=float)
    n = t.size
    ordered = n < 2 or bool(np.all(t[1:] >= t[:-1]))

    def between(lo: float, hi: float):
        """Samples with lo <= t < hi: a slice on ordered times (cheap), else a boolean mask."""
        if ordered:
            return slice(int(np.searchsorted(t, lo, "left")), int(np.searchsorted(t, hi, "left")))
        return (t >= lo) & (t < hi)

    def some(sel) -> bool:
        return sel.stop > sel.start if isinstance(sel, slice) else bool(sel.any())

    axis = np.asarray(plan.table_axis_level, dtype=float)
    steps = plan.steps
    C = np.empty((n, 3, 3))
    w = np.zeros((n, 3))
    ang = np.zeros(n)
    rate = np.zeros(n)
    idx = np.full(n, -1, dtype=np.int64)
    theta0 = 0.0  # table angle at the start of the current piece

    def rate_piece(mask, tstart, r0, r1, dur, cstart, th_start):
        tau = t[mask] - tstart
        rr = r0 + (r1 - r0) * (tau / dur if dur > 0 else 0.0)
        dth = r0 * tau + 0.5 * (r1 - r0) * tau**2 / (dur if dur > 0 else 1.0)
        C[mask] = rotation_about(axis, dth) @ cstart
        w[mask] = rr[:, None] * axis
        ang[mask] = th_start + dth
        rate[mask] = rr

    def rot_piece(mask, tstart, dur, c_from, c_to, th):
        rv = Rotation.from_matrix(c_to @ c_from.T).as_rotvec()
        phi = np.linalg.norm(rv)
        u = rv / phi if phi > 0 else axis
        tau = np.clip(t[mask] - tstart, 0.0, dur)
        s = 0.5 * (1 - np.cos(np.pi * tau / dur))
        sd = 0.5 * np.pi / dur * np.sin(np.pi * tau / dur)
        C[mask] = rotation_about(u, phi * s) @ c_from
        w[mask] = (phi * sd)[:, None] * u
        ang[mask] = th
        rate[mask] = 0.0

    # before the first step: spin up from rest (rate steps) or rest
    s0 = steps[0]
    c0 = np.asarray(s0.orientation_b2l)
    r0 = np.radians(s0.table_rate_dps)
    m = between(-np.inf, s0.start_s)
    if some(m):
        lead = s0.start_s
        # ramp 0 -> r0 over the lead time ending at C0
        cstart = rotation_about(axis, -0.5 * r0 * lead) @ c0
        rate_piece(m, 0.0, 0.0, r0, lead, cstart, -0.5 * r0 * lead)
        theta0 = 0.0
    for k, s in enumerate(steps):
        ck = np.asarray(s.orientation_b2l)
        rk = np.radians(s.table_rate_dps)
        m = between(s.start_s, s.end_s)
        rate_piece(m, s.start_s, rk, rk, s.duration_s, ck, theta0)
        idx[m] = k
        c_end = rotation_about(axis, rk * s.duration_s) @ ck
        th_end = theta0 + rk * s.duration_s
        if k + 1 < len(steps):
            nxt = steps[k + 1]
            cn = np.asarray(nxt.orientation_b2l)
            rn = np.radians(nxt.table_rate_dps)
            gap = nxt.start_s - s.end_s
            m = between(s.end_s, nxt.start_s)
            d_ang = _about_axis_angle(cn @ c_end.T, axis)
            ramp_ang = 0.5 * (rk + rn) * gap
            if d_ang is not None and _wrap_equal(d_ang, ramp_ang):
                rate_piece(m, s.end_s, rk, rn, gap, c_end, th_end)
                theta0 = th_end + ramp_ang
            else:
                g3 = gap / 3.0
                c_a = rotation_about(axis, rk * g3 / 2) @ c_end
                c_b = rotation_about(axis, -rn * g3 / 2) @ cn
                m1 = _sub(m, between(s.end_s, s.end_s + g3))
                m2 = _sub(m, between(s.end_s + g3, s.end_s + 2 * g3))
                m3 = _sub(m, between(s.end_s + 2 * g3, np.inf))
                rate_piece(m1, s.end_s, rk, 0.0, g3, c_end, th_end)
                th_a = th_end + rk * g3 / 2
                rot_piece(m2, s.end_s + g3, g3, c_a, c_b, th_a)
                rate_piece(m3, s.end_s + 2 * g3, 0.0, rn, g3, c_b, th_a)
                theta0 = th_a + rn * g3 / 2
        else:
            # after the plan the table decelerates to rest at TAIL_DECEL_RADPS2, then stays there
            ramp = abs(rk) / TAIL_DECEL_RADPS2
            m = between(s.end_s, s.end_s + ramp)
            if some(m):
                rate_piece(m, s.end_s, rk, 0.0, ramp, c_end, th_end)
            m = between(s.end_s + ramp, np.inf)
            if some(m):
                c_rest = rotation_about(axis, 0.5 * rk * ramp) @ c_end
                rate_piece(m, s.end_s + ramp, 0.0, 0.0, 1.0, c_rest, th_end + 0.5 * rk * ramp)
    return Trajectory(t, C, w, ang, rate, idx)



# ----------------------------------------------------------------------------------------------------------
# Opt-in cache for replicates: the kinematics of a plan at a time grid are the same in every replicate
# ----------------------------------------------------------------------------------------------------------
_CACHE: "OrderedDict[tuple, Trajectory] | None" = None
_CACHE_MAX = 64
CACHE_STATS = {"hits": 0, "subset_hits": 0, "misses": 0}
_SUBSET_SEEN: OrderedDict[tuple, None] = OrderedDict()


def _plan_key(plan) -> str:
    key = getattr(plan, "model_dump_json", None)
    text = key() if key else repr(plan)
    return hashlib.blake2b(text.encode(), digest_size=16).hexdigest()


def _take(tr: Trajectory, k: np.ndarray, t: np.ndarray) -> Trajectory:
    return Trajectory(t, tr.c_b2l[k], tr.omega_motion_level_radps[k], tr.table_angle_rad[k], tr.table_rate_radps[k],
                      tr.step_index[k])


def _lookup(plan, pk: str, t: np.ndarray):
    """A cached trajectory of this plan whose grid contains every requested time (indexing; bit-identical)."""
    for key, tr in reversed(_CACHE.items()):
        if key[0] != pk or not isinstance(tr, Trajectory) or tr.t_s.size < 2:
            continue
        g = tr.t_s
        dt = (g[-1] - g[0]) / (g.size - 1)
        if dt <= 0:
            continue
        k = np.rint((t - g[0]) / dt).astype(np.int64)
        np.clip(k, 0, g.size - 1, out=k)
        ok = g[k] == t
        if ok.all():
            return _take(tr, k, t)
        if ok.mean() > 0.5:  # the rest (window edges clipped to a step's bounds) computed and merged
            out = _take(tr, k, t)
            rest = _compute_trajectory(plan, t[~ok])
            arrays = [np.array(a) for a in (out.c_b2l, out.omega_motion_level_radps, out.table_angle_rad,
                                            out.table_rate_radps, out.step_index)]
            for a, r in zip(arrays, (rest.c_b2l, rest.omega_motion_level_radps, rest.table_angle_rad,
                                     rest.table_rate_radps, rest.step_index)):
                a[~ok] = r
            return Trajectory(t, *arrays)
    return None


@contextmanager
def kinematics_cache(max_entries: int = 64):
    """Within this block :func:`trajectory` memoises by (plan, times) and serves any subset of a cached time grid
    by indexing. Results are bit-identical to the uncached path (each sample's kinematics depend on its own time
    only); cached arrays are read-only, so a caller that writes into them fails loudly instead of corrupting it."""
    global _CACHE, _CACHE_MAX
    prev, prev_max = _CACHE, _CACHE_MAX
    _CACHE, _CACHE_MAX = OrderedDict() if prev is None else prev, max_entries
    try:
        yield CACHE_STATS
    finally:
        _CACHE, _CACHE_MAX = prev, prev_max


def trajectory(plan, t_s: np.ndarray) -> Trajectory:
    """Evaluate the plan's kinematics at times ``t_s`` (IMU clock, seconds from the first sample); memoised
    inside :func:`kinematics_cache`."""
    if _CACHE is None:
        return _compute_trajectory(plan, t_s)
    t = np.asarray(t_s, dtype=float)
    pk = _plan_key(plan)
    key = (pk, hashlib.blake2b(t.tobytes(), digest_size=16).hexdigest() + str(t.size))
    hit = _CACHE.get(key)
    if hit is not None:
        _CACHE.move_to_end(key)
        CACHE_STATS["hits"] += 1
        return hit
    tr = _lookup(plan, pk, t)
    if tr is not None:
        CACHE_STATS["subset_hits"] += 1
        if key not in _SUBSET_SEEN:  # kept under its own key from its second request on (a grid asked for again,
            _SUBSET_SEEN[key] = None  # e.g. the table log in every replicate), not for one-off windows
            while len(_SUBSET_SEEN) > 4 * _CACHE_MAX:
                _SUBSET_SEEN.popitem(last=False)
            return tr
    else:
        CACHE_STATS["misses"] += 1
        tr = _compute_trajectory(plan, t)
    tr = replace(tr, t_s=t.copy())  # the caller's array stays writeable
    for a in (tr.t_s, tr.c_b2l, tr.omega_motion_level_radps, tr.table_angle_rad, tr.table_rate_radps, tr.step_index):
        a.flags.writeable = False
    _CACHE[key] = tr
    while len(_CACHE) > _CACHE_MAX:
        _CACHE.popitem(last=False)
    return tr


@dataclass(frozen=True)
class BodyInputs:
    """True inputs in body axes at each sample: total angular rate, its earth-rate part, specific force."""

    omega_b_radps: np.ndarray
    omega_earth_b_radps: np.ndarray
    f_b_mps2: np.ndarray
    trajectory: Trajectory


def body_inputs(plan, t_s: np.ndarray, latitude_deg: float, gravity_mps2: float) -> BodyInputs:
    """omega_b = C_b^l^T (omega_table^l + omega_ie^l), f_b = C_b^l^T f^l ([SEED000] eq. 3-5, 14-16); memoised
    for identical requests inside :func:`kinematics_cache`."""
    key = None
    if _CACHE is not None:
        t = np.asarray(t_s, dtype=float)
        key = ("body", _plan_key(plan), hashlib.blake2b(t.tobytes(), digest_size=16).hexdigest() + str(t.size),
               float(latitude_deg), float(gravity_mps2))
        hit = _CACHE.get(key)
        if hit is not None:
            CACHE_STATS["hits"] += 1
            _CACHE.move_to_end(key)
            return hit
    tr = trajectory(plan, t_s)
    ct = np.swapaxes(tr.c_b2l, 1, 2)
    w_ie = earth_rate_level(latitude_deg, plan.frame)
    f_l = specific_force_level(gravity_mps2, plan.frame)
    w_e = ct @ w_ie
    w_motion = np.einsum("nij,nj->ni", ct, tr.omega_motion_level_radps)
    out = BodyInputs(w_motion + w_e, w_e, ct @ f_l, tr)
    if key is not None and _CACHE is not None:
        for a in (out.omega_b_radps, out.omega_earth_b_radps, out.f_b_mps2):
            a.flags.writeable = False
        _CACHE[key] = out
        while len(_CACHE) > _CACHE_MAX:
            _CACHE.popitem(last=False)
    return out


def consistent_plan_orientations(
    steps: list[dict], table_axis_level=(0.0, 0.0, 1.0)
) -> list[dict]:
    """Fill each step's ``orientation_b2l`` from its ``mount_b2l`` (orientation at table angle zero) so that
    consecutive rate steps on the same mount follow the linear ramp; returns new step dicts."""
    axis = np.asarray(table_axis_level, dtype=float)
    out = []
    theta = 0.0
    for k, s in enumerate(steps):
        s = dict(s)
        mount = np.asarray(s.pop("mount_b2l"), dtype=float)
        if k:
            prev = out[-1]
            pr = np.radians(prev["table_rate_dps"])
            rn = np.radians(s.get("table_rate_dps", 0.0))
            gap = s["start_s"] - (prev["start_s"] + prev["duration_s"])
            same = np.allclose(mount, prev_mount, atol=1e-12)
            theta = theta + pr * prev["duration_s"]
            if same:
                theta += 0.5 * (pr + rn) * gap
            else:
                theta += pr * gap / 6 + rn * gap / 6
        c = rotation_about(axis, theta) @ mount
        s["orientation_b2l"] = [list(map(float, row)) for row in c]
        out.append(s)
        prev_mount = mount
    return out
