"""The human report (HTML with embedded plots) and atomic writing of the three output files per device."""

from __future__ import annotations

import base64
import html
import io
import json
import os
import tempfile
from pathlib import Path

import numpy as np

_PLAIN_VIEW = {
    "plateau_residual": "a single plateau mean",
    "residual_vs_rate_squared": "the rate-plateau residuals, growing with rate squared",
    "residual_vs_rate_cubed": "the rate-plateau residuals, growing with rate cubed",
    "residual_vs_abs_rate": "the rate-plateau residuals, growing with |rate|",
    "residual_vs_temperature": "the plateau residuals, following temperature",
    "residual_vs_rate_x_temperature": "the rate-plateau residuals, following rate x temperature",
    "residual_vs_time_since_power_on": "the plateau residuals, drifting with time since power-on",
    "residual_vs_time_since_power_on_exp": "the plateau residuals, decaying after power-on",
    "residual_vs_visit_order": "the plateau residuals, following the visit order",
    "accel_rate_run_centripetal_x": "the accelerometer residuals of the rate runs, growing with rate squared",
    "accel_rate_run_centripetal_y": "the accelerometer residuals of the rate runs, growing with rate squared",
    "accel_rate_run_centripetal_z": "the accelerometer residuals of the rate runs, growing with rate squared",
    "table_angle_harmonic_1": "once-per-revolution ripple of the table angle",
    "table_angle_harmonic_2": "twice-per-revolution ripple of the table angle",
    "table_wobble_1rev": "once-per-revolution cross-axis signal (table wobble)",
    "clock_drift": "the table/IMU clock drift",
    "fit_chi2": "the scatter of the calibration fit residuals",
    "residual_spectrum_peak": "a spectral line of the static residual",
}


def plain_view(v: str) -> str:
    if v.startswith(("allan_band", "allan_level")):
        how = " (shape)" if v.startswith("allan_band") else " (level against the twin's noise model)"
        for sensor in ("gyro", "accel"):
            if f"_{sensor}_" in v:
                how += f", the three {sensor} axes " + ("combined" if "_axes_" in v else "pooled")
        if "_pooled_tau" in v:
            how += ", pooled over 3 octaves"
        return f"the Allan deviation of the long static record{how} at tau = {v.split('tau')[1]}"
    if v.startswith("static_residual_vs_f"):
        return "the static-position gyro residuals, growing with specific force squared"
    return _PLAIN_VIEW.get(v, v)


def answers(rep: dict) -> list[str]:
    """The three questions in plain words."""
    v = rep["verdict"]
    where = rep["where"]
    sh = rep["shrink"]
    out = []
    if v == "no_gap":
        out.append(f"No significant gap: the real runs are consistent with the fitted twin in every view "
                   f"(largest |z| {rep['gap']['z']:.1f}, smallest BH q {rep['gap']['p_value']:.2g}).")
        return out
    w = where[0] if where else None
    loc = ""
    if w:
        loc = (f"it lies in {plain_view(w['view'])}"
               + (f" of run {w['run_id']}" if w["run_id"] else " over all runs")
               + (f", channel {w['channel']}" if w["channel"] else "")
               + (f", step {w['step_index']}" if w["step_index"] is not None else "")
               + f" (z = {w['z']:.1f}, q = {w['q_value']:.2g})")
    out.append(f"Where: a gap of {sh['initial_floor_sd']:.1f} floor-sd (held-out error over the sim-vs-sim floor); {loc}.")
    if rep["effects"]:
        parts = []
        for e in rep["effects"]:
            ci = "" if e["ci_lo"] is None or not np.isfinite(e["ci_lo"]) else \
                f" (95 % interval {e['ci_lo']:.3g} to {e['ci_hi']:.3g})"
            parts.append(f"{e['family'].replace('_', ' ')}{' on ' + e['channel'] if e['channel'] else ''} of "
                         f"{e['magnitude']:.3g} {e['unit']}{ci}, held-out gain {e['delta_lpd']:.1f} "
                         f"({e['folds_positive']}/{e['folds']} folds positive)")
        out.append("Which: it is explained by " + "; then ".join(parts) + ".")
        amb = [a for a in rep["ambiguity"] if len(a) > 1]
        if amb:
            out.append("Ambiguous: the data cannot separate " + "; ".join(" / ".join(a) for a in amb) + ".")
        ci = sh["ratio_ci"]
        ci_s = "" if ci[0] is None else f" (interval {ci[0] * 100:.0f} % to " + \
            (f"{ci[1] * 100:.0f} %)" if ci[1] is not None else "unbounded)")
        out.append(f"How far it shrinks: modelled, the held-out gap shrinks by {sh['ratio'] * 100:.0f} %{ci_s}; "
                   f"{sh['remaining_floor_sd']:.1f} floor-sd remain. Verdict: {v.replace('_', ' ')}.")
        if sh.get("capped"):
            out.append(f"The shrink is capped at 100 % (uncapped {sh['ratio_uncapped'] * 100:.0f} %): after the fix the "
                       "held-out error lies below the sim-vs-sim floor, i.e. the twin's noise, fitted from runs that "
                       "carry the effect, is above the real noise, not an over-explained gap.")
        for e in rep["effects"]:
            lf = e.get("lack_of_fit")
            if lf and lf.get("significant"):
                out.append(f"The form of {e['family'].replace('_', ' ')} does not follow the gap on its own rows: a "
                           f"free level per plan step predicts the held-out runs better by {lf['delta_lpd']:.1f} "
                           f"(gate {lf['gate']:.1f}, {lf['folds_positive']}/{lf['folds']} folds), so an effect "
                           "outside the library remains.")
        if v == "partly_explained" and rep.get("views_after"):
            va = rep["views_after"][0]
            out.append(f"Still unexplained after the fix: {plain_view(va['view'])} (z = {va['z']:.1f}).")
    elif v == "noise_model":
        nr = rep.get("noise_refit") or {}
        terms = "; ".join(f"{ch}: " + ", ".join(f"{k} {v:.3g}" for k, v in t.items() if v)
                          for ch, t in (nr.get("terms_si") or {}).items())
        check = ("the re-estimated twin's replicates leave no deterministic view significant"
                 if nr.get("replicates_rerun") else "no deterministic view was significant")
        out.append("Which: no deterministic effect is supported; the gap is in the noise model (verdict noise model). "
                   "Re-estimated from the long static record (IEEE 952 terms + a Gauss-Markov term, SI); " + check
                   + (f": {terms}." if terms else "."))
    else:
        out.append("Which: no effect of the library explains it (verdict unexplained); nothing was forced onto the "
                   "nearest candidate.")
    return out


def _png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    import matplotlib.pyplot as plt

    plt.close(fig)
    return base64.b64encode(buf.getvalue()).decode()


def plots(diag) -> dict:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = {}
    vt = diag.views.table.head(25)
    fig, ax = plt.subplots(figsize=(8, 0.25 * len(vt) + 1))
    lab = [f"{r.view} {r.run_id or 'all'} {r.channel or ''} {'' if r.step_index != r.step_index or r.step_index is None else int(r.step_index)}"
           for r in vt.itertuples()]
    ax.barh(range(len(vt)), vt["z"].abs(), color=["C3" if s else "C0" for s in vt["significant"]])
    ax.set_yticks(range(len(vt)), lab, fontsize=7)
    ax.invert_yaxis()
    ax.axvline(4.0, color="k", ls="--", lw=0.8)
    ax.set_xlabel("|z| against the sim-vs-sim distribution (red: significant)")
    ax.set_title("Where: top views")
    out["where"] = _png(fig)
    E_base, E_model, floor = diag.plots["E"]
    fig, ax = plt.subplots(figsize=(5, 3))
    ax.hist(floor, bins=max(5, len(floor) // 3), color="0.7", label="sim-vs-sim floor (base replicates)")
    fa = diag.plots.get("E_floor_aug")
    if fa is not None and len(fa):
        ax.hist(fa, bins=max(5, len(fa) // 3), color="C2", alpha=0.4,
                label="floor after (augmented replicates, effects refitted)")
    ax.axvline(E_base, color="C3", label="real, base twin")
    ax.axvline(E_model, color="C2", ls="--", label="real, augmented twin")
    ax.set_xlabel("held-out whitened error E")
    ax.legend(fontsize=7)
    ax.set_title("Before / after")
    out["before_after"] = _png(fig)
    va = diag.views_after
    for i, e in enumerate(diag.plots["effects"]):
        names = [n for n in ("residual_vs", "accel_rate", "table_", "clock", "static_residual")]
        t = diag.views.table
        sub = t[t["view"].str.startswith(tuple(names)) & ((t["channel"] == e["channel"]) | (e["channel"] is None))].head(8)
        if sub.empty:
            continue
        fig, ax = plt.subplots(figsize=(6, 3))
        x = np.arange(len(sub))
        ax.errorbar(x, sub["rep_mean"], yerr=1.96 * sub["rep_sd"], fmt="s", color="0.5", label="simulated (base twin) 95 % band")
        ax.plot(x, sub["real"], "o", color="C3", label="real")
        if va is not None:
            m = va.table.set_index(["view", "run_id", "channel"])
            aft = []
            for r in sub.itertuples():
                try:
                    row = m.loc[(r.view, r.run_id, r.channel)]
                    row = row.iloc[0] if hasattr(row, "iloc") and row.ndim > 1 else row
                    aft.append((row["rep_mean"], row["rep_sd"]))
                except KeyError:
                    aft.append((np.nan, np.nan))
            aft = np.array(aft)
            ax.errorbar(x + 0.2, aft[:, 0], yerr=1.96 * aft[:, 1], fmt="^", color="C2", label="augmented twin 95 % band")
        ax.set_xticks(x, [f"{r.view.replace('residual_vs_', '')}\n{r.run_id or 'all'}" for r in sub.itertuples()],
                      fontsize=6, rotation=30)
        ax.set_ylabel("signature projection (whitened)")
        ax.set_title(f"{e['family']} {e['channel'] or ''}: residual against its signature")
        ax.legend(fontsize=6)
        out[f"effect_{i}"] = _png(fig)
    return out


def render_html(rep: dict, diag=None) -> str:
    e = html.escape
    figs = plots(diag) if diag is not None else {}
    parts = [(f"<html><head><meta charset='utf-8'><title>Sim-to-real diagnosis {e(rep['device_id'])}</title>"
              "<style>body{font-family:sans-serif;max-width:1000px;margin:auto}td,th{padding:2px 6px;font-size:12px}"
              "table{border-collapse:collapse}tr:nth-child(even){background:#f4f4f4}</style></head><body>"),
             f"<h1>Sim-to-real diagnosis: {e(rep['device_id'])}</h1>",
             (f"<p><b>Verdict: {e(rep['verdict'])}</b> ({len(rep['runs'])} runs; {rep.get('replicates', {}).get('base')} "
              "replicates of the fitted twin through the same segmentation and fits)</p><ul>")]
    parts += [f"<li>{e(a)}</li>" for a in answers(rep)]
    parts.append("</ul>")
    if "where" in figs:
        parts.append(f"<h2>Where</h2><img src='data:image/png;base64,{figs['where']}'>")
    for k, png in sorted(((diag.plots.get("extra_png") or {}) if diag is not None else {}).items()):
        parts.append(f"<p>{e(k)}</p><img src='data:image/png;base64,{png}'>")  # experiment-specific plots
    parts.append("<table><tr><th>view</th><th>run</th><th>channel</th><th>step</th><th>z</th><th>q</th></tr>")
    for w in rep["where"]:
        parts.append(f"<tr><td>{e(w['view'])}</td><td>{e(str(w['run_id']))}</td><td>{e(str(w['channel']))}</td>"
                     f"<td>{w['step_index'] if w['step_index'] is not None else ''}</td><td>{w['z']:.2f}</td>"
                     f"<td>{w['q_value']:.3g}</td></tr>")
    parts.append("</table>")
    if rep["effects"]:
        parts.append("<h2>Which</h2><table><tr><th>family</th><th>channel</th><th>magnitude</th><th>95 % interval</th>"
                     "<th>unit</th><th>held-out gain</th><th>folds +</th></tr>")
        for x in rep["effects"]:
            parts.append(f"<tr><td>{e(x['family'])}</td><td>{e(str(x['channel']))}</td><td>{x['magnitude']:.4g}</td>"
                         f"<td>{x['ci_lo']:.4g} .. {x['ci_hi']:.4g}</td><td>{e(x['unit'])}</td>"
                         f"<td>{x['delta_lpd']:.1f}</td><td>{x['folds_positive']}/{x['folds']}</td></tr>")
        parts.append("</table>")
        for k in sorted(f for f in figs if f.startswith("effect_")):
            parts.append(f"<img src='data:image/png;base64,{figs[k]}'>")
    parts.append("<h2>Candidates at the first step</h2><table><tr><th>family</th><th>channel</th><th>held-out gain</th>"
                 "<th>gate (sim-vs-sim calibrated)</th><th>folds +</th></tr>")
    for x in rep.get("selection_first_step", []):
        parts.append(f"<tr><td>{e(x['family'])}</td><td>{e(str(x['channel']))}</td><td>{x['delta_lpd']:.1f}</td>"
                     f"<td>{x['gate']:.1f}</td><td>{x['folds_positive']}/{x['folds']}</td></tr>")
    parts.append("</table>")
    if "before_after" in figs:
        parts.append(f"<h2>How far it shrinks</h2><img src='data:image/png;base64,{figs['before_after']}'>")
    sh = rep["shrink"]
    parts.append(f"<p>shrink ratio {sh['ratio']:.3f}, interval {sh['ratio_ci']}, initial gap "
                 f"{sh['initial_floor_sd']:.2f} floor-sd, remaining {sh['remaining_floor_sd']:.2f} floor-sd</p>")
    if rep.get("not_testable"):
        parts.append("<h2>Not testable here</h2><ul>")
        parts += [f"<li><b>{e(k)}</b>: {e(v)}</li>" for k, v in sorted(rep["not_testable"].items())]
        parts.append("</ul>")
    parts.append("</body></html>")
    return "\n".join(parts)


def write_atomic(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    with os.fdopen(fd, "w") as f:
        f.write(text)
    os.chmod(tmp, 0o644)
    os.replace(tmp, path)


def write_outputs(diag, out_dir: Path) -> dict:
    """DIR/<device>.json, DIR/<device>.html, DIR/<device>.twin.json (atomic)."""
    rep = diag.report
    dev = rep["device_id"]
    out_dir = Path(out_dir)
    paths = {"json": out_dir / f"{dev}.json", "html": out_dir / f"{dev}.html", "twin": out_dir / f"{dev}.twin.json"}
    write_atomic(paths["json"], json.dumps(_clean(rep), indent=1) + "\n")
    write_atomic(paths["html"], render_html(rep, diag))
    write_atomic(paths["twin"], json.dumps(_clean(diag.twin_file()), indent=1) + "\n")
    return paths


def _clean(x):
    """JSON-safe: NaN/inf -> null, numpy -> python."""
    if isinstance(x, dict):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return float(x) if np.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.ndarray):
        return _clean(x.tolist())
    return x
