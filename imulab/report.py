"""Console summaries of the store (what ``imulab run`` prints at the end)."""

from __future__ import annotations

from pathlib import Path

from pipelines.storage import VersionedStore


def print_outputs(store_dir: Path, echo=print) -> None:
    """Where every asset's outputs are, with partition counts, and any stage errors."""
    st = VersionedStore(Path(store_dir))
    echo(f"outputs under {Path(store_dir)}:")
    for asset in sorted(p.name for p in Path(store_dir).iterdir() if p.is_dir()) if Path(store_dir).is_dir() else []:
        parts = st.partitions(asset)
        if not parts:
            continue
        example = st.version_dir(asset, parts[0])
        echo(f"  {asset:<28} {len(parts):>4} partitions   e.g. {example}")
