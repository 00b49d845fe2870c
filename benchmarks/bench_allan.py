"""Allan deviation benchmark: allantools.oadev vs imulab (assets_lib.noise.allan), time and peak extra memory.

Every configuration runs in a fresh single-threaded subprocess (OPENBLAS/OMP/NUMBA threads = 1). Memory:
the subprocess builds its input, resets the kernel's peak-RSS counter (/proc/self/clear_refs = 5), runs the
call, and reports VmHWM minus the RSS before the call ("extra", also as a multiple of the input's size).
Data: rate at 100 Hz, white (0.1) + rate random walk (1e-4 sqrt(0.01)) + 0.5 offset, float64, fixed seed
(the series of the tests). Tau sets: 'octave' (allantools' octave m) and 'dense' (100 unique integer m
log-spaced from 1 to (N-1)/2), passed as the same explicit array to both libraries.

    python benchmarks/bench_allan.py                 # N = 5e7 (about 10 minutes on 2 cores)
    python benchmarks/bench_allan.py --n 1e7 --reps 3
Writes benchmarks/results/allan.json (or --out).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

WORKER = r"""
import json, os, sys, time, gc
import numpy as np
sys.path.insert(0, {root!r})
cfg = json.loads(sys.argv[1])

def status(key):
    with open('/proc/self/status') as fh:
        for line in fh:
            if line.startswith(key + ':'):
                return int(line.split()[1]) * 1024
    return -1

def make(n, seed, channels=1):
    rng = np.random.default_rng(seed)
    out = np.empty((n, channels)) if channels > 1 else np.empty(n)
    for c in range(channels):
        col = out[:, c] if channels > 1 else out
        blk = 1 << 22
        level = 0.0
        for a in range(0, n, blk):
            b = min(a + blk, n)
            w = rng.standard_normal(b - a)
            rw = np.cumsum(1e-4 * np.sqrt(0.01) * rng.standard_normal(b - a)) + level
            level = float(rw[-1])
            col[a:b] = 0.5 + 0.1 * w + rw
    return out

def taus_m(n, which):
    if which == 'octave':
        maxn = int(np.floor(np.log2(n)))
        m = np.unique(np.round(np.logspace(0, maxn, maxn + 1, base=2.0))).astype(np.int64)
        return m[m <= (n - 1) // 2]
    mmax = (n - 1) // 2
    k = 100
    while True:
        m = np.unique(np.round(np.logspace(0, np.log10(mmax), k)).astype(np.int64))
        if len(m) >= 100:
            return m
        k += 1

n = cfg['n']
m = taus_m(n, cfg['taus'])
method = cfg['method']

def warm(al, backend):
    # compile / load every kernel outside the measurement (window, chain, spill block)
    small = np.cumsum(np.random.default_rng(0).standard_normal(200_000))
    saved = (al.kernels.M_CHAIN, al.streaming.SMALL_SPAN)
    al.kernels.M_CHAIN, al.streaming.SMALL_SPAN = 1 << 10, 1 << 12
    try:
        al.oadev(small, 100.0, 'dense', backend=backend, alpha=0)
        al.allan_stream_array(small, 100.0, 'dense', backend=backend, alpha=0)
    finally:
        al.kernels.M_CHAIN, al.streaming.SMALL_SPAN = saved

if method in ('allantools', 'imulab', 'imulab_numpy'):
    y = make(n, 1)
    import allantools
    from assets_lib.noise import allan as al
    if method != 'allantools':
        warm(al, 'numba' if method == 'imulab' else 'numpy')
elif method == 'six':
    y = make(n, 1, channels=cfg['channels']).reshape(n, -1)
    from assets_lib.noise import allan as al
    warm(al, 'auto')
elif method == 'stream':
    from assets_lib.noise import allan as al
    warm(al, 'auto')
    y = None
gc.collect()
input_bytes = int(y.nbytes) if y is not None else int(cfg.get('input_bytes', 0))
rss0 = status('VmRSS')
with open('/proc/self/clear_refs', 'w') as fh:
    fh.write('5')
t0 = time.perf_counter()
if method == 'allantools':
    _, dev, _, _ = allantools.oadev(y, rate=100.0, data_type='freq', taus=m / 100.0)
elif method in ('imulab', 'imulab_numpy'):
    r = al.oadev(y, 100.0, m / 100.0, backend='numba' if method == 'imulab' else 'numpy', alpha=0)
    dev = r.adev
elif method == 'six':
    res = al.allan_deviations(y, 100.0, m / 100.0, alpha=0)
    dev = np.concatenate([v.adev for v in res.values()])
elif method == 'stream':
    res = al.allan_parquet(cfg['path'], 100.0, ['y'], m / 100.0, alpha=0)
    dev = res['y'].adev
elapsed = time.perf_counter() - t0
peak = status('VmHWM')
np.save(cfg['out'], dev)
print(json.dumps({{'seconds': elapsed, 'rss_before': rss0, 'peak': peak, 'extra_bytes': peak - rss0,
                  'input_bytes': input_bytes, 'n_taus': int(len(m))}}))
"""


def run(cfg: dict) -> dict:
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", NUMBA_NUM_THREADS="1",
               MKL_NUM_THREADS="1")
    code = WORKER.format(root=str(ROOT))
    p = subprocess.run([sys.executable, "-c", code, json.dumps(cfg)], capture_output=True, text=True, env=env)
    if p.returncode != 0:
        raise RuntimeError(f"{cfg['method']} failed:\n{p.stderr[-3000:]}")
    return json.loads(p.stdout.strip().splitlines()[-1])


def write_parquet(path: Path, n: int) -> int:
    """The same series as the workers' make(), written by row groups (bounded memory here too)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    rng = np.random.default_rng(1)
    blk = 1 << 22
    level = 0.0
    schema = pa.schema([pa.field("y", pa.float64())])
    with pq.ParquetWriter(path, schema, compression="snappy") as w:
        for a in range(0, n, blk):
            b = min(a + blk, n)
            wn = rng.standard_normal(b - a)
            rw = np.cumsum(1e-4 * np.sqrt(0.01) * rng.standard_normal(b - a)) + level
            level = float(rw[-1])
            w.write_table(pa.table({"y": 0.5 + 0.1 * wn + rw}), row_group_size=1 << 20)
    return n * 8


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=float, default=5e7)
    ap.add_argument("--reps", type=int, default=1)
    ap.add_argument("--six-n", type=float, default=None, help="samples per channel of the 6-channel test")
    ap.add_argument("--skip-allantools", action="store_true")
    ap.add_argument("--skip-numpy", action="store_true")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "allan.json")
    args = ap.parse_args(argv)
    n = int(args.n)
    six_n = int(args.six_n or n)
    tmp = Path(tempfile.mkdtemp(prefix="bench_allan_"))
    rows = []
    devs = {}

    def do(method, taus, **extra):
        times, mems = [], []
        n_run = extra.pop("n", n)
        tag = f"{method}{extra.get('channels', '')}_{taus}"
        for rep in range(args.reps):
            cfg = {"method": method, "taus": taus, "n": n_run, "out": str(tmp / f"{tag}.npy"), **extra}
            r = run(cfg)
            times.append(r["seconds"])
            mems.append(r)
            print(f"  {method:13s} {taus:6s} n={cfg['n']:.3g} rep {rep}: {r['seconds']:.2f} s, extra "
                  f"{r['extra_bytes'] / 1e6:.0f} MB ({r['extra_bytes'] / max(r['input_bytes'], 1):.2f}x input), "
                  f"{r['n_taus']} taus", flush=True)
        devs[(method, taus)] = np.load(cfg["out"])
        row = {"method": method, "taus": taus, "n": cfg["n"], "n_taus": mems[0]["n_taus"],
               "seconds_median": float(np.median(times)), "seconds": times,
               "extra_mb": max(m["extra_bytes"] for m in mems) / 1e6,
               "extra_x_input": max(m["extra_bytes"] for m in mems) / max(mems[0]["input_bytes"], 1),
               "peak_rss_mb": max(m["peak"] for m in mems) / 1e6}
        rows.append(row)
        return row

    print(f"N = {n:.3g}, single thread, {platform.processor() or platform.machine()}, python {platform.python_version()}")
    res = {}
    for taus in ("octave", "dense"):
        if not args.skip_allantools:
            res[("allantools", taus)] = do("allantools", taus)
        res[("imulab", taus)] = do("imulab", taus)
        if not args.skip_numpy:
            res[("imulab_numpy", taus)] = do("imulab_numpy", taus)
    print("  writing parquet ...", flush=True)
    path = tmp / "y.parquet"
    input_bytes = write_parquet(path, n)
    res[("stream", "dense")] = do("stream", "dense", path=str(path), input_bytes=input_bytes)
    res[("stream", "octave")] = do("stream", "octave", path=str(path), input_bytes=input_bytes)
    res[("six1", "dense")] = do("six", "dense", n=six_n, channels=1)
    res[("six6", "dense")] = do("six", "dense", n=six_n, channels=6)

    summary = {}
    for taus in ("octave", "dense"):
        s = {}
        if ("allantools", taus) in res:
            a = res[("allantools", taus)]["seconds_median"]
            s["speedup_imulab_vs_allantools"] = a / res[("imulab", taus)]["seconds_median"]
            if ("imulab_numpy", taus) in res:
                s["speedup_imulab_numpy_vs_allantools"] = a / res[("imulab_numpy", taus)]["seconds_median"]
            ref = devs[("allantools", taus)]
            s["max_rel_diff_vs_allantools"] = float(np.max(np.abs(devs[("imulab", taus)] / ref - 1.0)))
        s["stream_slowdown_vs_in_memory"] = res[("stream", taus)]["seconds_median"] / res[("imulab", taus)]["seconds_median"]
        s["stream_identical_to_in_memory"] = bool(np.array_equal(devs[("stream", taus)], devs[("imulab", taus)]))
        s["stream_peak_rss_mb"] = res[("stream", taus)]["peak_rss_mb"]
        s["stream_extra_mb"] = res[("stream", taus)]["extra_mb"]
        s["imulab_extra_x_input"] = res[("imulab", taus)]["extra_x_input"]
        if ("allantools", taus) in res:
            s["allantools_extra_x_input"] = res[("allantools", taus)]["extra_x_input"]
        summary[taus] = s
    summary["six_channels_time_ratio"] = res[("six6", "dense")]["seconds_median"] / res[("six1", "dense")]["seconds_median"]
    doc = {
        "what": "allantools.oadev vs imulab assets_lib.noise.allan.oadev, single thread, fresh process per run",
        "n": n,
        "reps": args.reps,
        "machine": {"cpus": os.cpu_count(), "processor": platform.processor(), "python": platform.python_version(),
                    "loadavg_at_end": os.getloadavg()},
        "runs": rows,
        "summary": summary,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(doc, indent=1))
    shutil.rmtree(tmp, ignore_errors=True)
    print(json.dumps(summary, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
