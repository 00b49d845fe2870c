"""The HTML calibration certificate of one record, and the check that a certificate shows what its record says.

Every certified value a reader sees sits in an element carrying ``data-k`` (its key in ``certified_cells``), and the
record itself is embedded as canonical JSON (``<script type="application/json" id="imulab-record">``). A
certificate is genuine when (``certificate_problems``): the embedded record's hash is the hash of its content, every
``data-k`` text equals the rendering of the embedded record (no cell edited, added or removed), and the whole page
equals the rendering of the embedded record with the page's own plots (no text added elsewhere). ``imulab verify
CERT.html`` then verifies the embedded record against the raw archive and the chain like a JSON record.

Values are printed rounded to their uncertainty: the standard uncertainty to two significant digits and the value
to the same decimal place (JCGM 100:2008, GUM section 7.2.6).
"""

from __future__ import annotations

import base64
import html
import json
import math
from dataclasses import dataclass, field
from html.parser import HTMLParser

from assets_lib.records.canonical import canonical_json, content_sha256
from assets_lib.records.diff import coefficient_id, noise_id

#: bumped whenever the rendering changes (the full-page comparison applies to certificates of the same format)
CERTIFICATE_FORMAT = "2"
UNCERTAINTY_DIGITS = 2
#: alt text of the navigation-budget plot and id of the embedded device calibration it was computed from
NAV_PLOT = "navigation budget"
DEVICE_CALIBRATION_ID = "imulab-device-calibration"

_CSS = """body{font-family:Helvetica,Arial,sans-serif;margin:2em;color:#222;max-width:70em}
table{border-collapse:collapse;margin:0.6em 0 1.4em 0;font-size:0.88em}
td,th{border:1px solid #bbb;padding:0.25em 0.6em;text-align:left}th{background:#eee}
td.num{text-align:right;font-family:monospace}code{font-size:0.85em;word-break:break-all}
.muted{color:#777}h1{font-size:1.5em}h2{font-size:1.15em;margin-top:1.6em}img{max-width:100%;border:1px solid #ddd}
.banner{padding:0.8em 1em;margin:1em 0;border-radius:4px;font-weight:bold}
.invalid{background:#c62828;color:#fff}.invalid ul{font-weight:normal;margin:0.4em 0 0 0}
.valid{background:#e8f5e9;color:#1b5e20;border:1px solid #a5d6a7}"""


# ---------------------------------------------------------------------------------------------------------------
# Rounding to the uncertainty
# ---------------------------------------------------------------------------------------------------------------
def _finite(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _exp10(x: float) -> int:
    return math.floor(math.log10(abs(x))) if x else 0


def _last_digit(u: float, digits: int = UNCERTAINTY_DIGITS) -> int:
    """Decimal exponent of the last printed digit when ``u`` is shown to ``digits`` significant digits."""
    last = _exp10(u) - (digits - 1)
    if round(u / 10.0**last) >= 10**digits:  # 9.96 -> 10: one digit fewer after rounding
        last += 1
    return last


def _format_at(x: float, last: int, exponent: int | None) -> str:
    """``x`` rounded to the digit 10**last, fixed-point (``exponent`` None) or as mantissa x 10**exponent."""
    if exponent is None:
        return f"{round(x, -last):.{max(0, -last)}f}" if last <= 0 else f"{round(x / 10.0**last) * 10**last:d}"
    return f"{x / 10.0**exponent:.{max(0, exponent - last)}f}e{exponent:+03d}"


def _style(value: float, u: float, last: int) -> int | None:
    """Fixed-point for magnitudes 1e-3 .. 1e6 resolved to at most 9 decimals, else a common exponent."""
    e = _exp10(max(abs(value), u))
    return None if -3 <= e < 6 and last >= -9 else e


def round_to_uncertainty(value, u, digits: int = UNCERTAINTY_DIGITS) -> tuple[str, str]:
    """(value, uncertainty) as printed: ``u`` to ``digits`` significant digits, ``value`` to the same decimal
    place, both in the same notation (GUM 7.2.6). Without a usable uncertainty the value gets 6 digits."""
    if not _finite(value):
        return "n/a", (format_sig(u, digits) if _finite(u) else "n/a")
    if not _finite(u) or u <= 0:
        return f"{value:.6g}", "n/a"
    last = _last_digit(u, digits)
    ex = _style(value, u, last)
    return _format_at(value, last, ex), _format_at(u, last, ex)


def format_sig(x, digits: int = UNCERTAINTY_DIGITS) -> str:
    """``x`` to ``digits`` significant digits ('n/a' when absent)."""
    if not _finite(x):
        return "n/a"
    if x == 0:
        return "0"
    last = _last_digit(x, digits)
    return _format_at(x, last, _style(x, abs(x), last))


def format_interval(value, lo, hi, upper_bound: bool) -> tuple[str, str]:
    """A noise term and its interval rounded to its half-width: ('value', '[lo, hi]') or ('< hi', '')."""
    if upper_bound or not _finite(value):
        return (f"< {format_sig(hi)}" if _finite(hi) else "n/a"), ""
    half = (hi - lo) / 2.0 if _finite(lo) and _finite(hi) and hi > lo else None
    if half is None:
        return f"{value:.6g}", ""
    last = _last_digit(half)
    ex = _style(value, max(abs(lo), abs(hi)), last)
    return _format_at(value, last, ex), f"[{_format_at(lo, last, ex)}, {_format_at(hi, last, ex)}]"


def _g(v, digits: int) -> str:
    return f"{v:.{digits}g}" if _finite(v) else "n/a"


# ---------------------------------------------------------------------------------------------------------------
# What a certificate shows: one text per certified key
# ---------------------------------------------------------------------------------------------------------------
def record_id(record: dict) -> str:
    c = record["content"]
    return f"{c['device']['id']}/{c['run']['run_id']}"


def certified_cells(record: dict) -> dict[str, str]:
    """Every certified text of the certificate of ``record``, by key (what ``data-k`` elements show)."""
    c = record["content"]
    dev, run, tc = c["device"], c["run"], c["test_conditions"]
    temp = tc.get("temperature_degc") or {}
    status = c.get("status")
    cells = {
        "record_id": record_id(record),
        "record_sha256": record["record_sha256"],
        "prev_record_sha256": c.get("prev_record_sha256") or "none (first record)",
        "record_schema_version": record["record_schema_version"],
        "status": {"valid": "valid calibration", "invalid": "NOT A VALID CALIBRATION"}.get(status, "not assessed"),
        "device": f"{dev['id']} ({dev['model']}, {dev['grade']} grade" + (f", serial {dev['serial']}" if dev.get("serial")
                                                                         else "") + ")",
        "test": f"{run['test_kind']}, started {run['start_time_utc']}, power cycle {run['power_cycle_index']}",
        "site": f"{tc['site']['name']}, latitude {_g(tc['latitude_deg'], 8)} deg, height {_g(tc['site']['height_m'], 6)} m",
        "gravity": f"{_g(tc['gravity_mps2'], 9)} m/s^2 ({tc['site']['gravity_model']})",
        "temperature": (f"{_g(temp.get('min'), 4)} to {_g(temp.get('max'), 4)} degC (mean {_g(temp.get('mean'), 4)})"
                        if temp else "not recorded"),
        "plan": f"{tc['plan']['name']}: {tc['plan']['n_steps']} steps ({tc['plan']['n_rate_steps']} rate, "
                f"{tc['plan']['n_static_steps']} static), {_g(tc['plan']['duration_s'], 6)} s, frame {tc['plan']['frame']}",
        "samples": f"{run['n_samples']} at {_g(run['sample_rate_hz'], 6)} Hz"
                   + (f", table {run['table_id']}" if run.get("table_id") else ""),
    }
    for i, why in enumerate(c.get("status_reasons") or []):
        cells[f"status_reason/{i}"] = why
    for r in c["coefficients"]:
        k = f"coef/{coefficient_id(r)}"
        if r["observable"]:
            v, u = round_to_uncertainty(r["value_lab"], r["stderr_lab"])
            cells[f"{k}/value_lab"], cells[f"{k}/stderr_lab"] = v, u
            cells[f"{k}/expanded_lab"] = format_sig(2 * r["stderr_lab"] if _finite(r["stderr_lab"]) else None)
            cells[f"{k}/value"], cells[f"{k}/stderr"] = round_to_uncertainty(r["value"], r["stderr"])
        else:
            cells[f"{k}/value_lab"] = "not observable with this plan"
        cells[f"{k}/unit_lab"], cells[f"{k}/unit"], cells[f"{k}/method"] = r["unit_lab"], r["unit"], r["method"]
    for r in c.get("noise") or []:
        k = f"noise/{noise_id(r)}"
        up = bool(r.get("is_upper_bound"))
        cells[f"{k}/value_lab"], cells[f"{k}/interval_lab"] = format_interval(r.get("value_lab"), r.get("ci_lo_lab"),
                                                                               r.get("ci_hi_lab"), up)
        cells[f"{k}/value"], cells[f"{k}/interval"] = format_interval(r.get("value"), r.get("ci_lo"), r.get("ci_hi"), up)
        cells[f"{k}/unit_lab"], cells[f"{k}/unit"] = str(r.get("unit_lab")), str(r.get("unit"))
        cells[f"{k}/ci_level"] = _g(r.get("ci_level"), 3)
    for name, h in c["raw_files"].items():
        cells[f"raw/{name}"] = h
    sw = c["software"]
    cells["software/imulab"] = str(sw.get("imulab_version"))
    cells["software/git_commit"] = str(sw.get("git_commit")) + (" (working tree modified)" if sw.get("git_dirty") else "")
    for a, s in c["stages"].items():
        cells[f"stage/{a}"] = f"code version {s['code_version']}, output version {s['version']}"
    return cells


def navigation_cells(device_calibration) -> tuple[dict[str, str], list[str], object]:
    """The navigation budget's certified texts (``nav/<row>/calibrated|uncalibrated``), row labels (HTML) and the
    budget, computed deterministically from the device calibration the certificate embeds
    (``assets_lib.navigation.budget.certificate_budget``: closed-form alignment, 1 h at-rest strapdown)."""
    from assets_lib.navigation.budget import budget_rows, certificate_budget

    budget = certificate_budget(device_calibration)
    cells, labels = {}, []
    for i, (label, cal, unc) in enumerate(budget_rows(budget)):
        cells[f"nav/{i}/calibrated"], cells[f"nav/{i}/uncalibrated"] = html.unescape(cal), html.unescape(unc)
        labels.append(label)
    return cells, labels, budget


def device_calibration_problems(record: dict, doc) -> tuple[object | None, list[str]]:
    """(Calibration, problems) of the device calibration embedded beside a record: its own hash, its date (the
    record's start), its device, and every term it takes from this record equal to the record's value. Terms from
    the device's earlier records are named by run id and record sha256 (in the calibration and on the page); they
    are not checked against those records here (the certificate embeds only its own record)."""
    from assets_lib.apply.model import CalibrationError, calibration_from_json, to_utc

    try:
        cal = calibration_from_json(doc)
    except (CalibrationError, KeyError, TypeError, ValueError) as e:
        return None, [f"certificate: the embedded device calibration cannot be read ({e})"]
    c = record["content"]
    problems = []
    if cal.device_id != c["device"]["id"]:
        problems.append(f"certificate: the embedded device calibration is of device {cal.device_id!r}, the record "
                        f"of {c['device']['id']!r}")
    if cal.at_utc is None or to_utc(cal.at_utc) != to_utc(c["run"]["start_time_utc"]):
        problems.append(f"certificate: the embedded device calibration is at {cal.at_utc}, not at the record's start "
                        f"{c['run']['start_time_utc']}")
    rows = {(r["sensor"], r["axis"], r["coefficient"], r.get("source")): r for r in c.get("coefficients", [])}
    for t in cal.terms:
        if t.run_id != c["run"]["run_id"]:
            continue
        r = rows.get((t.sensor, t.axis, t.coefficient, t.source))
        if t.record_sha256 != record["record_sha256"] or r is None or r.get("value") != t.value:
            problems.append(f"certificate: the embedded device calibration's {t.sensor} {t.axis} {t.coefficient} "
                            f"from run {t.run_id} is not this record's value")
    return cal, problems


# ---------------------------------------------------------------------------------------------------------------
# Rendering
# ---------------------------------------------------------------------------------------------------------------
def _e(v) -> str:
    return html.escape("" if v is None else str(v))


def certificate_html(record: dict, plots: dict[str, bytes] | None = None, device_calibration=None,
                     navigation=None) -> str:
    """Human-readable certificate of one record: validity banner, record id and hash, conditions, coefficient
    table with standard and expanded (k = 2) uncertainties in lab and SI units rounded to the uncertainty, noise
    terms with intervals, raw file hashes, software and stage versions, the residual / Allan plots embedded as
    base64 PNG, and the record itself as canonical JSON (for ``imulab verify CERT.html``).

    With ``device_calibration`` (``assets_lib.navigation.budget.certificate_calibration``: the device's
    calibration at the record's start) also what it buys in navigation: a small table and plot, with the device
    calibration embedded as hashed JSON so that ``imulab verify`` recomputes every printed budget value.
    ``navigation``: ``navigation_cells(device_calibration)`` when the caller computed it already (the check
    renders the page again and must not integrate the budget twice)."""
    c = record["content"]
    cells = certified_cells(record)
    plots = dict(plots or {})
    nav_png = plots.pop(NAV_PLOT, None)
    if device_calibration is not None:
        nav_cells, nav_labels, budget = navigation or navigation_cells(device_calibration)
        cells.update(nav_cells)
        if nav_png is None:
            from assets_lib.navigation.budget import budget_plot_png

            nav_png = budget_plot_png(budget)
    dev, run = c["device"], c["run"]

    def td(key: str, cls: str = "", tag: str = "td", code: bool = False) -> str:
        text = _e(cells[key])
        inner = f"<code>{text}</code>" if code else text
        return f"<{tag}{' class=' + cls if cls else ''} data-k='{_e(key)}'>{inner}</{tag}>"

    def kv(rows) -> str:
        return "<table>" + "".join(f"<tr><th>{_e(label)}</th>{td(key, code=code)}</tr>" for label, key, code in rows) \
            + "</table>"

    parts = [f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'><title>Calibration certificate "
             f"{_e(dev['id'])} {_e(run['run_id'])}</title><style>{_CSS}</style></head>"
             f"<body data-imulab-certificate='{CERTIFICATE_FORMAT}'>",
             f"<h1>Calibration certificate: {_e(dev['id'])}, run {_e(run['run_id'])}</h1>"]
    if c.get("status") == "invalid":
        parts.append("<div class='banner invalid' role='alert'>" + td("status", tag="span")
                     + ": this record is not a valid calibration of the device. Reasons:<ul>"
                     + "".join(f"<li>{td(f'status_reason/{i}', tag='span')}</li>"
                               for i in range(len(c.get("status_reasons") or []))) + "</ul></div>")
    else:
        parts.append("<div class='banner valid'>Status: " + td("status", tag="span")
                     + " (coefficients plausible for the grade, residuals consistent with the noise model)</div>")
    parts.append(kv([("Record", "record_id", False), ("Record sha256", "record_sha256", True),
                     ("Previous record sha256", "prev_record_sha256", True), ("Device", "device", False),
                     ("Test", "test", False), ("Record schema", "record_schema_version", False)]))
    parts.append("<h2>Test conditions</h2>" + kv([("Site", "site", False), ("Local gravity", "gravity", False),
                                                  ("Temperature", "temperature", False), ("Plan", "plan", False),
                                                  ("Samples", "samples", False)]))
    parts.append("<h2>Coefficients</h2>")
    if c["coefficients"]:
        parts.append("<table><tr><th>Source</th><th>Sensor</th><th>Axis</th><th>Coefficient</th><th>Value</th>"
                     "<th>Std. uncertainty</th><th>Expanded U (k=2)</th><th>Unit</th><th>Value (SI)</th>"
                     "<th>Std. unc. (SI)</th><th>SI unit</th><th>Method</th></tr>")
        for r in c["coefficients"]:
            k = f"coef/{coefficient_id(r)}"
            nums = (td(f"{k}/value_lab", "num") + td(f"{k}/stderr_lab", "num") + td(f"{k}/expanded_lab", "num")
                    if r["observable"] else
                    f"<td colspan=3 class=muted data-k='{_e(k)}/value_lab'>{_e(cells[k + '/value_lab'])}</td>")
            si = (td(f"{k}/value", "num") + td(f"{k}/stderr", "num") if r["observable"]
                  else "<td class=num>n/a</td><td class=num>n/a</td>")
            parts.append(f"<tr><td>{_e(r['source'])}</td><td>{_e(r['sensor'])}</td><td>{_e(r['axis'])}</td>"
                         f"<td>{_e(r['coefficient'])}</td>{nums}{td(k + '/unit_lab')}{si}{td(k + '/unit')}"
                         f"{td(k + '/method')}</tr>")
        parts.append("</table><p class=muted>Standard uncertainty = the fit's standard error (1 sigma); expanded "
                     "uncertainty U = 2 x standard uncertainty (approx. 95 % coverage). Values are rounded to their "
                     "uncertainty (two significant digits); the record holds them in full precision.</p>")
    else:
        parts.append("<p class=muted>No coefficients are fitted from this test kind.</p>")
    if c.get("noise"):
        parts.append("<h2>Noise terms</h2><table><tr><th>Source</th><th>Channel</th><th>Term</th><th>Method</th>"
                     "<th>Value</th><th>Interval</th><th>Unit</th><th>Value (SI)</th><th>Interval (SI)</th>"
                     "<th>SI unit</th><th>Level</th></tr>")
        for r in c["noise"]:
            k = f"noise/{noise_id(r)}"
            parts.append(f"<tr><td>{_e(r.get('source'))}</td><td>{_e(r.get('channel'))}</td>"
                         f"<td>{_e(r.get('parameter'))}</td><td>{_e(r.get('method'))}</td>"
                         + "".join(td(f"{k}/{f}", "num" if f not in ("unit_lab", "unit") else "")
                                   for f in ("value_lab", "interval_lab", "unit_lab", "value", "interval", "unit",
                                             "ci_level")) + "</tr>")
        parts.append("</table><p class=muted>Intervals at the stated confidence level (chi-square, Allan deviation); "
                     "'&lt; x' is an upper bound (term not resolved).</p>")
    for name, png in (plots or {}).items():
        parts.append(f"<h2>{_e(name)}</h2><img alt='{_e(name)}' src='data:image/png;base64,"
                     f"{base64.b64encode(png).decode()}'>")
    if device_calibration is not None:
        from assets_lib.navigation.budget import budget_note, used_records_note

        parts.append("<h2>What the calibration buys in navigation</h2><p class=muted>"
                     + _e(budget_note(budget) + used_records_note(device_calibration))
                     + " Recomputed by imulab verify from the device calibration embedded in this page.</p>"
                     "<table><tr><th>Quantity</th><th>Calibrated (1&sigma;)</th><th>Uncalibrated</th></tr>"
                     + "".join(f"<tr><td>{label}</td>{td(f'nav/{i}/calibrated', 'num')}"
                               f"{td(f'nav/{i}/uncalibrated', 'num')}</tr>" for i, label in enumerate(nav_labels))
                     + f"</table><img alt='{NAV_PLOT}' src='data:image/png;base64,{base64.b64encode(nav_png).decode()}'>")
    parts.append("<h2>Raw data (sha256)</h2>" + kv([(n, f"raw/{n}", True) for n in c["raw_files"]]))
    parts.append("<h2>Software</h2>" + kv([("imulab", "software/imulab", False), ("git commit", "software/git_commit", True),
                                           *[(f"stage {a}", f"stage/{a}", False) for a in c["stages"]]]))
    pv = record.get("provenance", {})
    parts.append(f"<p class=muted>Created {_e(pv.get('created_utc'))} by Dagster run {_e(pv.get('dagster_run_id'))}. "
                 "Verify with <code>imulab verify " + _e(run["run_id"]) + ".html</code> (or the .json): it checks "
                 "that this page shows its record, recomputes the coefficients from the raw archive and checks the "
                 "hash chain.</p>")
    embedded = canonical_json(record).decode("utf-8").replace("<", "\\u003c")
    parts.append(f"<script type='application/json' id='imulab-record'>{embedded}</script>")
    if device_calibration is not None:
        doc = canonical_json(device_calibration.to_json()).decode("utf-8").replace("<", "\\u003c")
        parts.append(f"<script type='application/json' id='{DEVICE_CALIBRATION_ID}'>{doc}</script>")
    parts.append("</body></html>\n")
    return "".join(parts)


# ---------------------------------------------------------------------------------------------------------------
# Reading a certificate back
# ---------------------------------------------------------------------------------------------------------------
@dataclass
class ParsedCertificate:
    format: str | None = None
    record: dict | None = None
    device_calibration: dict | None = None
    cells: dict[str, list[str]] = field(default_factory=dict)  # key -> texts shown (a key shown twice is an edit)
    plots: dict[str, bytes] = field(default_factory=dict)


class _Parser(HTMLParser):
    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.out = ParsedCertificate()
        self._stack: list[tuple[str, str | None]] = []  # (tag, data-k)
        self._text: dict[int, list[str]] = {}
        self._script: list[str] | None = None
        self._script_id: str | None = None
        self._h2 = None

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "body":
            self.out.format = a.get("data-imulab-certificate")
        if tag == "script" and a.get("id") in ("imulab-record", DEVICE_CALIBRATION_ID):
            self._script, self._script_id = [], a.get("id")
            return
        if tag == "img" and (a.get("src") or "").startswith("data:image/png;base64,"):
            self.out.plots[a.get("alt") or f"plot {len(self.out.plots)}"] = base64.b64decode(a["src"].split(",", 1)[1])
            return
        if tag in ("meta", "img", "br", "hr", "link", "input"):
            return
        self._stack.append((tag, a.get("data-k")))
        if a.get("data-k") is not None:
            self._text[len(self._stack)] = []

    def handle_endtag(self, tag):
        if tag == "script" and self._script is not None:
            try:
                doc = json.loads("".join(self._script))
            except json.JSONDecodeError:
                doc = None
            if self._script_id == DEVICE_CALIBRATION_ID:
                self.out.device_calibration = doc if doc is not None else "unreadable"
            else:
                self.out.record = doc
            self._script = None
            return
        while self._stack:
            depth = len(self._stack)
            t, key = self._stack.pop()
            if key is not None:
                self.out.cells.setdefault(key, []).append("".join(self._text.pop(depth, [])))
            if t == tag:
                break

    def handle_data(self, data):
        if self._script is not None:
            self._script.append(data)
            return
        for depth in self._text:
            self._text[depth].append(data)


def parse_certificate(text: str) -> ParsedCertificate:
    p = _Parser()
    p.feed(text)
    p.close()
    return p.out


def certificate_problems(text: str) -> tuple[dict | None, list[str]]:
    """(embedded record, named problems) of a certificate page: the record's own hash, every shown certified
    value against the record, and the whole page against the rendering of the record."""
    cert = parse_certificate(text)
    if cert.record is None or not isinstance(cert.record, dict) or "content" not in cert.record:
        return None, ["certificate: no embedded record (script#imulab-record missing or not JSON); it cannot be "
                      "tied to a record"]
    rec, problems = cert.record, []
    got = content_sha256(rec["content"])
    if got != rec.get("record_sha256"):
        problems.append(f"certificate: the embedded record's sha256 {str(rec.get('record_sha256'))[:16]}... is not "
                        f"the hash of its content ({got[:16]}...): the embedded record was edited")
    try:
        want = certified_cells(rec)
    except (KeyError, TypeError) as e:
        return rec, problems + [f"certificate: the embedded record is incomplete ({type(e).__name__}: {e})"]
    device_cal = nav = None
    if cert.device_calibration is not None:
        device_cal, more = device_calibration_problems(rec, cert.device_calibration)
        problems += more
        if device_cal is not None:
            nav = navigation_cells(device_cal)
            want.update(nav[0])
    for key in sorted(set(want) | set(cert.cells), key=str):
        shown = cert.cells.get(key, [])
        if key not in want:
            problems.append(f"certificate: shows {key} = {shown[0]!r}, which the record does not hold")
        elif not shown:
            problems.append(f"certificate: {key} (record: {want[key]!r}) is not shown")
        elif len(shown) > 1 or shown[0] != want[key]:
            problems.append(f"certificate: {key} shows {' / '.join(map(repr, shown))}, the record gives {want[key]!r}")
    if not problems and cert.format == CERTIFICATE_FORMAT \
            and certificate_html(rec, cert.plots, device_cal, nav) != text:
        problems.append("certificate: the page differs from the rendering of its record outside the value cells "
                        "(text added or changed)")
    if cert.format != CERTIFICATE_FORMAT:
        problems.append(f"certificate: format {cert.format!r}, this imulab renders format {CERTIFICATE_FORMAT!r}; "
                        "only the value cells were compared")
    return rec, problems

