"""Console summaries of the store (what ``imulab run`` prints at the end)."""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from assets_lib.store import VersionedStore

_HEADLINE = [
    ("gyro_rate_fit", "gyro", "scale_factor"),
    ("gyro_rate_fit", "gyro", "bias"),
    ("accel_multiposition_fit", "accel", "scale_factor"),
    ("accel_multiposition_fit", "accel", "bias"),
]


def record_statuses(st: VersionedStore) -> dict[tuple[str, str], tuple[str, str]]:
    """(device, run id) -> (status, reasons) of every record in the devices' current ``calibration_record``."""
    import json

    out = {}
    for dev in st.partitions("calibration_record"):
        for f in sorted(st.version_dir("calibration_record", dev).glob("*.json")):
            if f.name == "meta.json":
                continue
            try:
                c = json.loads(f.read_text()).get("content", {})
            except (OSError, ValueError):
                continue
            if c.get("status") is not None:
                out[(dev, f.stem)] = (str(c["status"]), "; ".join(map(str, c.get("status_reasons") or [])))
    return out


def headline_coefficients(st: VersionedStore, skipped: list[str] | None = None) -> pd.DataFrame:
    """Latest run's headline coefficients per device (value +- stderr in lab units), one row per device/axis.
    Runs whose calibration record is not valid are skipped (the latest valid run is shown); each skip is
    appended to ``skipped`` as one line naming the run and the record's reasons."""
    status = record_statuses(st)
    rows = []
    for asset, sensor, coef in _HEADLINE:
        runs: dict[str, list[str]] = {}
        for k in st.partitions(asset):
            runs.setdefault(k.split("__", 1)[0], []).append(k)
        for dev, keys in sorted(runs.items()):
            for k in sorted(keys, reverse=True):
                st_, why = status.get((dev, k.split("__", 1)[1]), ("valid", ""))
                if st_ == "valid":
                    break
                if skipped is not None:
                    line = f"{dev} {k.split('__', 1)[1]}: record {st_} ({why or 'no reason given'}); not shown"
                    if line not in skipped:
                        skipped.append(line)
            else:
                continue  # no valid run of this device for this coefficient
            c = st.read(asset, k, "coefficients")
            c = c[(c.sensor == sensor) & (c.coefficient == coef)]
            for _, r in c.iterrows():
                rows.append({"device": dev, "run": k.split("__", 1)[1], "axis": r.axis,
                             f"{sensor} {coef}": f"{r.value_lab:.4g} +- {r.stderr_lab:.2g} {r.unit_lab}"})
    if not rows:
        return pd.DataFrame()
    df = pd.DataFrame(rows)
    return df.groupby(["device", "axis"], as_index=False).first()


def current_certificates(st: VersionedStore, device: str) -> Path | None:
    """The folder of the device's certificates when they were rendered from its current record version, else None."""
    rec, cert = st.current_version("calibration_record", device), st.current_version("certificate", device)
    if rec is None or cert is None or st.read_meta("certificate", device, cert).get("record_version") != rec:
        return None
    return st.version_dir("certificate", device, cert)


def print_outputs(store_dir: Path, echo=print) -> None:
    """Where every asset's outputs are, headline coefficients, certificates and drift plots."""
    st = VersionedStore(Path(store_dir))
    echo(f"outputs under {Path(store_dir)}  (<asset>/<partition>/<version>/, CURRENT names the version in use):")
    assets = sorted(p.name for p in Path(store_dir).iterdir() if p.is_dir()) if Path(store_dir).is_dir() else []
    for asset in assets:
        parts = st.partitions(asset)
        if parts:
            echo(f"  {asset:<26} {len(parts):>4} partitions")
    skipped: list[str] = []
    head = headline_coefficients(st, skipped)
    if len(head):
        echo("\nheadline coefficients (latest run per device with a valid record; value +- standard error):")
        echo(head.drop(columns=[c for c in ("run",) if c in head]).to_string(index=False))
    for line in skipped:
        echo(f"  skipped, invalid record: {line}")
    missing = []
    for dev in st.partitions("calibration_record"):
        d = st.version_dir("calibration_record", dev)
        recs = sorted(p for p in d.glob("*.json") if p.name != "meta.json")
        echo(f"\ncalibration records of {dev}: {d}  ({len(recs)} records, e.g. {recs[-1].name if recs else '-'})")
        certs = current_certificates(st, dev)
        if certs is None:
            missing.append(dev)
        else:
            echo(f"  certificates: {certs}  ({len(list(certs.glob('*.html')))} HTML, verify with `imulab verify "
                 f"{certs / '<run>.html'}`)")
    if missing:
        echo(f"\ncertificates (HTML) not rendered for the current records of {len(missing)} device(s) "
             f"({', '.join(missing[:5])}{', ...' if len(missing) > 5 else ''}): `imulab certificates` with this run's "
             "options renders them into <store>/certificate/<device>/ (or `imulab run --certificates`)")
    if "fleet_drift" in assets and st.partitions("fleet_drift"):
        d = st.version_dir("fleet_drift", st.partitions("fleet_drift")[0])
        echo(f"\nfleet drift: {d / 'drift.parquet'}")
    if any(st.partitions(a) for a in assets):
        echo("figures (segmentation, residual, Allan, drift plots): `imulab plots` draws them from the store")
    if "sim_to_real" in assets and st.partitions("sim_to_real"):
        echo("\nsim-to-real diagnosis (verdict per device, its report):")
        for dev in st.partitions("sim_to_real"):
            d = st.version_dir("sim_to_real", dev)
            verdict = st.read_meta("sim_to_real", dev).get("verdict", "?")
            echo(f"  {dev:<10} {verdict:<17} {d / (dev + '.html')}")
