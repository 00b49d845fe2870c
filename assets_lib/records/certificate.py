"""The HTML calibration certificate of one record."""

from __future__ import annotations

import base64
import html


_CSS = """body{font-family:Helvetica,Arial,sans-serif;margin:2em;color:#222;max-width:70em}
table{border-collapse:collapse;margin:0.6em 0 1.4em 0;font-size:0.88em}
td,th{border:1px solid #bbb;padding:0.25em 0.6em;text-align:left}th{background:#eee}
td.num{text-align:right;font-family:monospace}code{font-size:0.85em;word-break:break-all}
.muted{color:#777}h1{font-size:1.5em}h2{font-size:1.15em;margin-top:1.6em}img{max-width:100%;border:1px solid #ddd}"""


def _e(v) -> str:
    return html.escape("" if v is None else str(v))


def _fmt(v, digits: int = 6) -> str:
    return "n/a" if v is None else f"{v:.{digits}g}"


def _kv_table(pairs) -> str:
    return "<table>" + "".join(f"<tr><th>{_e(k)}</th><td>{v}</td></tr>" for k, v in pairs) + "</table>"


def certificate_html(record: dict, plots: dict[str, bytes] | None = None) -> str:
    """Human-readable certificate of one record: conditions, coefficient table with standard and expanded (k = 2)
    uncertainties in lab units (SI value in full precision alongside), noise terms, raw file hashes, software,
    chain hashes, and the residual / Allan plots embedded as base64 PNG."""
    c = record["content"]
    dev, run, tc = c["device"], c["run"], c["test_conditions"]
    temp = tc.get("temperature_degc") or {}
    parts = [f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'><title>Calibration certificate "
             f"{_e(dev['id'])} {_e(run['run_id'])}</title><style>{_CSS}</style></head><body>",
             f"<h1>Calibration certificate: {_e(dev['id'])}, run {_e(run['run_id'])}</h1>",
             _kv_table([
                 ("Device", f"{_e(dev['id'])} ({_e(dev['model'])}, {_e(dev['grade'])} grade"
                            + (f", serial {_e(dev['serial'])}" if dev.get("serial") else "") + ")"),
                 ("Test", f"{_e(run['test_kind'])}, started {_e(run['start_time_utc'])}, power cycle "
                          f"{_e(run['power_cycle_index'])}"),
                 ("Record sha256", f"<code>{_e(record['record_sha256'])}</code>"),
                 ("Previous record sha256", f"<code>{_e(c.get('prev_record_sha256') or 'none (first record)')}</code>"),
                 ("Record schema", _e(record["record_schema_version"])),
             ]),
             "<h2>Test conditions</h2>",
             _kv_table([
                 ("Site", f"{_e(tc['site']['name'])}, latitude {_fmt(tc['latitude_deg'], 8)} deg, height "
                          f"{_fmt(tc['site']['height_m'])} m"),
                 ("Local gravity", f"{_fmt(tc['gravity_mps2'], 9)} m/s^2 ({_e(tc['site']['gravity_model'])})"),
                 ("Temperature", f"{_fmt(temp.get('min'), 4)} to {_fmt(temp.get('max'), 4)} degC (mean "
                                 f"{_fmt(temp.get('mean'), 4)})" if temp else "not recorded"),
                 ("Plan", f"{_e(tc['plan']['name'])}: {tc['plan']['n_steps']} steps ({tc['plan']['n_rate_steps']} "
                          f"rate, {tc['plan']['n_static_steps']} static), {_fmt(tc['plan']['duration_s'])} s, "
                          f"frame {_e(tc['plan']['frame'])}"),
                 ("Samples", f"{run['n_samples']} at {_fmt(run['sample_rate_hz'])} Hz"
                             + (f", table {_e(run['table_id'])}" if run.get("table_id") else "")),
             ])]
    coefs = c["coefficients"]
    parts.append("<h2>Coefficients</h2>")
    if coefs:
        parts.append("<table><tr><th>Source</th><th>Sensor</th><th>Axis</th><th>Coefficient</th><th>Value</th>"
                     "<th>Std. uncertainty</th><th>Expanded U (k=2)</th><th>Unit</th><th>Value (SI)</th>"
                     "<th>Std. unc. (SI)</th><th>SI unit</th><th>Method</th></tr>")
        for r in coefs:
            obs = r["observable"]
            parts.append(
                f"<tr><td>{_e(r['source'])}</td><td>{_e(r['sensor'])}</td><td>{_e(r['axis'])}</td>"
                f"<td>{_e(r['coefficient'])}</td>"
                + (f"<td class=num>{_fmt(r['value_lab'], 7)}</td><td class=num>{_fmt(r['stderr_lab'], 3)}</td>"
                   f"<td class=num>{_fmt(2 * r['stderr_lab'] if r['stderr_lab'] is not None else None, 3)}</td>"
                   if obs else "<td colspan=3 class=muted>not observable with this plan</td>")
                + f"<td>{_e(r['unit_lab'])}</td><td class=num>{_e(repr(r['value']) if r['value'] is not None else 'n/a')}"
                f"</td><td class=num>{_e(repr(r['stderr']) if r['stderr'] is not None else 'n/a')}</td>"
                f"<td>{_e(r['unit'])}</td><td>{_e(r['method'])}</td></tr>")
        parts.append("</table><p class=muted>Standard uncertainty = the fit's standard error (1 sigma); expanded "
                     "uncertainty U = 2 x standard uncertainty (approx. 95 % coverage).</p>")
    else:
        parts.append("<p class=muted>No coefficients are fitted from this test kind.</p>")
    if c.get("noise"):
        cols = [k for k in c["noise"][0] if k not in ("device_id", "run_id")]
        parts.append("<h2>Noise terms</h2><table><tr>" + "".join(f"<th>{_e(k)}</th>" for k in cols) + "</tr>")
        for r in c["noise"]:
            parts.append("<tr>" + "".join(
                f"<td class=num>{_fmt(r.get(k), 6)}</td>" if isinstance(r.get(k), float) else f"<td>{_e(r.get(k))}</td>"
                for k in cols) + "</tr>")
        parts.append("</table>")
    for name, png in (plots or {}).items():
        parts.append(f"<h2>{_e(name)}</h2><img alt='{_e(name)}' src='data:image/png;base64,"
                     f"{base64.b64encode(png).decode()}'>")
    parts.append("<h2>Raw data (sha256)</h2>" + _kv_table([(n, f"<code>{_e(h)}</code>") for n, h in
                                                          c["raw_files"].items()]))
    sw = c["software"]
    parts.append("<h2>Software</h2>" + _kv_table(
        [("imulab", _e(sw.get("imulab_version"))),
         ("git commit", f"<code>{_e(sw.get('git_commit'))}</code>" + (" (working tree modified)" if sw.get("git_dirty")
                                                                      else "")),
         *[(f"stage {a}", f"code version {_e(s['code_version'])}, output version <code>{_e(s['version'])}</code>")
           for a, s in c["stages"].items()]]))
    pv = record.get("provenance", {})
    parts.append(f"<p class=muted>Created {_e(pv.get('created_utc'))} by Dagster run {_e(pv.get('dagster_run_id'))}. "
                 "Verify with <code>imulab verify " + _e(run["run_id"]) + ".json</code>: it recomputes the "
                 "coefficients from the raw archive and checks the hash chain.</p></body></html>\n")
    return "".join(parts)
