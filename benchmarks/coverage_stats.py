"""Shared scoring of the coverage benchmarks (mc_calibration_coverage.py, coverage_noise.py): targets,
trial-clustered coverage / z statistics, and writing the result files."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pandas as pd

Z95 = 1.959963984540054
TARGET_COVERAGE = (0.93, 0.97)
TARGET_MEAN_Z = 0.1
TARGET_SD_Z = (0.9, 1.1)


def clustered(d: pd.DataFrame) -> dict:
    """Coverage, mean z and sd z with trial-clustered standard errors (cluster-robust ratio estimators: the
    estimates of one trial share a device)."""
    g = d.groupby("trial")
    n_t = g.size().to_numpy(float)
    N, T = n_t.sum(), len(n_t)
    corr = T / (T - 1) if T > 1 else np.nan
    c_t = g["covered"].sum().to_numpy(float)
    cov = c_t.sum() / N
    out = {"n": int(N), "trials": T, "coverage": cov, "coverage_se": float(np.sqrt(corr * np.sum((c_t - cov * n_t) ** 2)) / N)}
    dz = d[np.isfinite(d["z"].to_numpy(float))]
    if len(dz) > 1:
        gz = dz.groupby("trial")
        nz = gz.size().to_numpy(float)
        s1 = gz["z"].sum().to_numpy(float)
        s2 = gz["z"].apply(lambda v: float(np.sum(v**2))).to_numpy(float)
        Nz = nz.sum()
        mz, m2 = s1.sum() / Nz, s2.sum() / Nz
        sd = float(np.sqrt(max(m2 - mz**2, 0.0) * Nz / max(Nz - 1, 1)))
        cz = len(nz) / (len(nz) - 1) if len(nz) > 1 else np.nan
        out.update(mean_z=mz, mean_z_se=float(np.sqrt(cz * np.sum((s1 - mz * nz) ** 2)) / Nz), sd_z=sd,
                   sd_z_se=float(np.sqrt(cz * np.sum((s2 - m2 * nz) ** 2)) / Nz / (2 * sd)) if sd > 0 else np.nan)
    else:
        out.update(mean_z=np.nan, mean_z_se=np.nan, sd_z=np.nan, sd_z_se=np.nan)
    return out


def chi2_pivot_z(x: float, nu: float) -> float:
    """Phi^-1(F_chi2(x; nu)): standard normal when x ~ chi2_nu (the z of a variance's chi-square interval)."""
    from scipy import stats

    return float(stats.norm.ppf(np.clip(stats.chi2.cdf(x, nu), 1e-12, 1 - 1e-12)))


def run_budgeted(fn, jobs: list, workers: int = 1, budget_s: float | None = None) -> list[dict]:
    """``fn(job)`` (a list of rows) over ``jobs``, on ``workers`` processes; with ``budget_s`` no job starts after that
    many seconds (every job started runs to its end: a shared machine's honest partial run instead of a killed one)."""
    t0 = time.time()
    recs: list[dict] = []
    if workers > 1:
        from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

        with ProcessPoolExecutor(workers) as ex:
            it, pending = iter(jobs), set()
            while True:
                while len(pending) < 2 * workers and (budget_s is None or time.time() - t0 < budget_s):
                    j = next(it, None)
                    if j is None:
                        break
                    pending.add(ex.submit(fn, j))
                if not pending:
                    break
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for f in done:
                    recs.extend(f.result())
    else:
        for j in jobs:
            if budget_s is not None and time.time() - t0 >= budget_s:
                break
            recs.extend(fn(j))
    return recs


def meets_two_sided(r) -> bool:
    """Coverage within TARGET_COVERAGE and, where z exists, |mean z| and sd z within their targets."""
    ok = TARGET_COVERAGE[0] <= r["coverage"] <= TARGET_COVERAGE[1]
    if np.isfinite(r["mean_z"]):
        ok &= abs(r["mean_z"]) < TARGET_MEAN_Z and TARGET_SD_Z[0] <= r["sd_z"] <= TARGET_SD_Z[1]
    return bool(ok)


def fmt(v, se=None, f="{:.3f}"):
    if v is None or not np.isfinite(v):
        return "-"
    return f.format(v) + (f" ± {se:.3f}" if se is not None and np.isfinite(se) else "")


def table_lines(t: pd.DataFrame, cols: list[str]) -> list[str]:
    """Markdown header and rows of a summary table: ``cols`` (e.g. family, grade), n, coverage, mean z and sd z with
    their trial-clustered standard errors, meets."""
    lines = ["| " + " | ".join(cols) + " | n | coverage | mean z | sd z | meets |",
             "|" + "---|" * len(cols) + "---:|---:|---:|---:|---|"]
    for r in t.to_dict("records"):
        lines.append("| " + " | ".join(str(r[c]) for c in cols) + f" | {r['n']} | {fmt(r['coverage'], r['coverage_se'])} | "
                     f"{fmt(r['mean_z'], r['mean_z_se'], '{:+.3f}')} | {fmt(r['sd_z'], r['sd_z_se'])} | "
                     f"{'yes' if r['meets'] else 'no'} |")
    return lines


def write_results(out: Path, tabs: dict[str, pd.DataFrame], meta: dict, text: str, records: pd.DataFrame | None) -> None:
    """``out``.md (the text), .json (meta and every table) and, when given, .records.csv (every scored estimate)."""
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".md").write_text(text)
    if records is not None:
        records.to_csv(out.with_suffix(".records.csv"), index=False)
    out.with_suffix(".json").write_text(json.dumps(
        {"meta": meta, **{k: t.to_dict(orient="records") for k, t in tabs.items()}}, indent=1, default=float) + "\n")
