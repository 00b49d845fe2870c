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


def headline_coefficients(st: VersionedStore) -> pd.DataFrame:
    """Latest run's headline coefficients per device (value +- stderr in lab units), one row per device/axis."""
    rows = []
    for asset, sensor, coef in _HEADLINE:
        latest: dict[str, str] = {}
        for k in st.partitions(asset):
            dev = k.split("__", 1)[0]
            latest[dev] = max(latest.get(dev, k), k)
        for dev, k in sorted(latest.items()):
            c = st.read(asset, k, "coefficients")
            c = c[(c.sensor == sensor) & (c.coefficient == coef)]
            for _, r in c.iterrows():
                rows.append({"device": dev, "run": k.split("__", 1)[1], "axis": r.axis,
                             f"{sensor} {coef}": f"{r.value_lab:.4g} +- {r.stderr_lab:.2g} {r.unit_lab}"})
    if not rows:
        return pd.DataFrame()
    df = pd.DataFrame(rows)
    return df.groupby(["device", "axis"], as_index=False).first()


def print_outputs(store_dir: Path, echo=print) -> None:
    """Where every asset's outputs are, headline coefficients, certificates and drift plots."""
    st = VersionedStore(Path(store_dir))
    echo(f"outputs under {Path(store_dir)}  (<asset>/<partition>/<version>/, CURRENT names the version in use):")
    assets = sorted(p.name for p in Path(store_dir).iterdir() if p.is_dir()) if Path(store_dir).is_dir() else []
    for asset in assets:
        parts = st.partitions(asset)
        if parts:
            echo(f"  {asset:<26} {len(parts):>4} partitions")
    head = headline_coefficients(st)
    if len(head):
        echo("\nheadline coefficients (latest run per device; value +- standard error):")
        echo(head.drop(columns=[c for c in ("run",) if c in head]).to_string(index=False))
    for dev in st.partitions("calibration_record"):
        d = st.version_dir("calibration_record", dev)
        certs = sorted(d.glob("*.html"))
        if certs:
            echo(f"\ncalibration records of {dev}: {d}  ({len(certs)} certificates, e.g. {certs[-1].name})")
    if "fleet_drift" in assets and st.partitions("fleet_drift"):
        d = st.version_dir("fleet_drift", st.partitions("fleet_drift")[0])
        echo(f"\nfleet drift: {d / 'drift.parquet'}  plots: {', '.join(p.name for p in sorted(d.glob('*.png')))}")
