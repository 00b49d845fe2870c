"""Sim-to-real diagnosis of the real table-free sessions in ../shared/data (docs/simreal.md sec. 10).

    python benchmarks/realdata_diagnosis.py --replicates 20 [--data ../shared/data] [--workers 1]

Imports imu_tk's Xsens session and imucal's two Ferraris sessions with ``imulab import`` into a temporary landing
folder (the sources are only read), runs ``imulab diagnose``'s code on each device, and writes the reports to
``benchmarks/results/realdata_diagnosis/<device>.json`` and the plots to ``docs/figures/simreal_real_<device>_*.png``
(where-map and the table-free views).
"""

from __future__ import annotations

import argparse
import base64
import json
import os
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

#: imu_tk's Xsens session: the import options of docs/realdata.md sec. 5, where each number is justified (raw
#: unsigned 16-bit counts, zero at mid-scale 32768; accelerometer gain 0.0024 m/s^2 and gyro gain 0.00021 rad/s per
#: count, imu_tk's fitted K to two figures). The single definition: tests/test_diagnosis_tablefree.py imports it and
#: checks it against the doc's command. (Before Nov 2026 the diagnosis used accel_lsb=0.0024, gyro_lsb=1/6258 and no
#: zero counts: a 79 m/s^2 / 5.2 rad/s offset and a gyro gain 1.31x off, which the import now warns about.)
XSENS_IMPORT_OPTS = ["--gravity-mps2", "9.81744", "-o", "accel_lsb=0.0024", "-o", "accel_zero_count=32768",
                     "-o", "gyro_lsb=0.00021", "-o", "gyro_zero_count=32768", "-o", "initial_static_s=50"]

SESSIONS = {
    "xsens": ("imu_tk", ["imu_tk_xsens/xsens_acc.mat", "imu_tk_xsens/xsens_gyro.mat"], XSENS_IMPORT_OPTS),
    "bmi160": ("imucal", ["imucal_example/annotated_session.csv"],
               ["--gravity-mps2", "9.81", "-o", "sample_rate_hz=204.8", "-o", f"accel_lsb={1 / 2048}",
                "-o", f"gyro_lsb={1 / 16.4}"]),
    "imucal-example": ("imucal", ["imucal_example/example_ferraris_session.csv"],
                       ["--gravity-mps2", "9.81", "-o", "sample_rate_hz=102.4",
                        "-o", "sections={data}/imucal_example/example_ferraris_session_list.json"]),
}


def main(argv=None):
    from click.testing import CliRunner

    from assets_lib.simreal.diagnose import diagnose_device
    from assets_lib.simreal.report import _clean, plots, write_atomic
    from assets_lib.simreal.tablefree_diagnose import figures
    from imulab.cli import main as cli

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=os.environ.get("IMULAB_SHARED_DATA", str(REPO.parent / "shared" / "data")))
    ap.add_argument("--replicates", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--device", action="append", choices=sorted(SESSIONS))
    a = ap.parse_args(argv)
    data = Path(a.data)
    out = REPO / "benchmarks" / "results" / "realdata_diagnosis"
    figs = REPO / "docs" / "figures"
    with tempfile.TemporaryDirectory() as tmp:
        land = Path(tmp) / "land"
        for dev in a.device or sorted(SESSIONS):
            fmt, srcs, opts = SESSIONS[dev]
            r = CliRunner().invoke(cli, ["import", fmt, *[str(data / s) for s in srcs], "--landing", str(land),
                                         "--device-id", dev, "--run-id", "session",
                                         *[o.format(data=data) for o in opts]])
            if r.exit_code != 0:
                raise SystemExit(f"import {dev}: {r.output}")
            for line in r.output.splitlines():  # e.g. the importer's warning on counts that look unscaled
                if "WARN" in line:
                    print(f"import {dev}: {line}", flush=True)
            t0 = time.time()
            d = diagnose_device(land, dev, replicates=a.replicates, seed=a.seed, workers=a.workers,
                                progress=lambda m: print(m, flush=True))
            rep = _clean({**d.report, "wall_s": time.time() - t0})
            write_atomic(out / f"{dev}.json", json.dumps(rep, indent=1) + "\n")
            p = plots(d)
            (figs / f"simreal_real_{dev}_where.png").write_bytes(base64.b64decode(p["where"]))
            for png in figures(d).values():  # one run per imported session
                (figs / f"simreal_real_{dev}_views.png").write_bytes(png)
            eff = ", ".join(f"{e['family']}/{e['channel']} {e['magnitude']:.3g} [{e['ci_lo']:.3g}, {e['ci_hi']:.3g}] "
                            f"{e['unit']}" for e in rep["effects"]) or "-"
            print(f"{dev}: verdict {rep['verdict']}; gap z {rep['gap']['z']:.1f}; effects {eff}; shrink "
                  f"{rep['shrink']['ratio']:.2f}; {rep['wall_s']:.0f} s", flush=True)


if __name__ == "__main__":
    main()
