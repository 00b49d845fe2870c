"""``imulab plots``: draw the figures of stored stage outputs (plateau segmentation, rate and multi-position
residuals, Allan deviation, fleet drift charts) into a folder, on demand.

``imulab run`` stores tables only (drawing cost more CPU than the science, issue 10 item 8); the figure functions
(``assets_lib.stages.figures``) draw each figure from a partition's current stored version and the inputs it was
computed from. Output: ``OUT/<asset>/<partition>/<figure>.png`` (default OUT: <data>/plots), each written atomically.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import click


@click.command("plots")
@click.option("--store", "store", type=click.Path(file_okay=False), default=None,
              help="Versioned outputs (default: <data>/store).")
@click.option("--data-dir", default="imulab_data", show_default=True, help="Working folder of `imulab run`.")
@click.option("--out", type=click.Path(file_okay=False), default=None, help="Output folder (default: <data>/plots).")
@click.option("--asset", "assets", multiple=True, metavar="STAGE", help="Only this stage's figures; repeatable.")
@click.option("--partition", "partitions", multiple=True, metavar="KEY",
              help="Only this partition (capture key DEV__RUN, device id, or 'fleet'), or all captures of a device "
                   "id; repeatable.")
def command(store, data_dir, out, assets, partitions):
    """Draw the figures of the current stored outputs into a folder (PNG per figure)."""
    import warnings

    from assets_lib.stages.figures import FIGURES, figures, view_of
    from assets_lib.store import VersionedStore

    warnings.filterwarnings("ignore")
    store = Path(store or Path(data_dir) / "store")
    if not store.is_dir():
        raise click.BadParameter(f"{store} is not a store folder (run `imulab run` first)", param_hint="--store")
    out = Path(out or Path(data_dir) / "plots")
    unknown = sorted(set(assets) - set(FIGURES))
    if unknown:
        raise click.BadParameter(f"no figures for {unknown}; stages with figures: {sorted(FIGURES)}",
                                 param_hint="--asset")
    st = VersionedStore(store)
    n, failed = 0, []
    for asset in assets or FIGURES:
        for key in st.partitions(asset):
            if partitions and key not in partitions and key.split("__", 1)[0] not in partitions:
                continue
            view = view_of(st, asset, key)
            if view is None:  # a version a gate rejected is drawn too: its figures show why
                continue
            try:
                pngs = figures(asset, key, view)
            except Exception as e:  # noqa: BLE001 - one figure that cannot be drawn must not stop the others
                failed.append(f"{asset} {key}: {type(e).__name__}: {e}")
                continue
            for name, png in pngs.items():
                _write_atomic(out / asset / key / f"{name}.png", png)
                n += 1
    click.echo(f"{n} figure(s) drawn into {out.resolve()}  (<asset>/<partition>/<figure>.png)")
    for f in failed:
        click.echo(f"  FAILED {f}", err=True)
    raise SystemExit(1 if failed else 0)


def _write_atomic(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
