"""Reading a device's stored records and checking its hash chain: edited, missing and unlinked records, named."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd

from assets_lib.records.canonical import content_sha256
from assets_lib.records.content import run_order_key


def load_records_dir(directory: str | Path) -> tuple[dict[str, dict], pd.DataFrame | None]:
    """Records (``<run_id>.json`` carrying ``record_schema_version``) and ``records.parquet`` of a version folder."""
    d = Path(directory)
    recs = {}
    for p in sorted(d.glob("*.json")):
        try:
            r = json.loads(p.read_text(encoding="utf-8"))
        except (json.JSONDecodeError, UnicodeDecodeError):
            recs[p.stem] = {"_unreadable": str(p)}
            continue
        if isinstance(r, dict) and "record_schema_version" in r:
            recs[p.stem] = r
    listing = pd.read_parquet(d / "records.parquet") if (d / "records.parquet").is_file() else None
    return recs, listing


def self_hash_problem(record: dict, name: str = "") -> str | None:
    """A record whose stored hash is not the hash of its content was edited after it was made."""
    if "_unreadable" in record:
        return f"record {name}: not valid JSON ({record['_unreadable']})"
    got = content_sha256(record.get("content", {}))
    if got != record.get("record_sha256"):
        return (f"record of run {name or record['content']['run']['run_id']}: stored record_sha256 "
                f"{str(record.get('record_sha256'))[:16]}... is not the sha256 of its content ({got[:16]}...): "
                "the record was edited")
    return None


def chain_problems(records: dict[str, dict], listing: pd.DataFrame | None = None, expected_runs=None,
                   up_to_run: str | None = None) -> list[str]:
    """Every break of a device's hash chain, named: edited records, missing records, broken links.

    ``records``: run id -> record; ``listing``: records.parquet of the same version (the device's index);
    ``expected_runs``: (run_id, start_time_utc) of the device's runs in the archive; ``up_to_run``: only the chain
    up to and including this run is checked."""
    problems = []
    good = {rid: r for rid, r in records.items() if "_unreadable" not in r}
    problems += [p for rid, r in records.items() if (p := self_hash_problem(r, rid))]
    order = {rid: run_order_key(r["content"]["run"]["start_time_utc"], rid) for rid, r in good.items()}
    listed = {}
    if listing is not None:
        for row in listing.itertuples():
            listed[row.run_id] = (row.record_sha256, row.start_time_utc)
            order.setdefault(row.run_id, run_order_key(row.start_time_utc, row.run_id))
    for rid, start in expected_runs or []:
        order.setdefault(rid, run_order_key(start, rid))
    limit = order.get(up_to_run) if up_to_run else None
    in_scope = lambda rid: limit is None or order[rid] <= limit  # noqa: E731
    for rid, (sha, _) in sorted(listed.items(), key=lambda kv: order[kv[0]]):
        if not in_scope(rid):
            continue
        if rid not in records:
            problems.append(f"record of run {rid} is missing (records.parquet lists it with sha256 {sha[:16]}...): "
                            "deleted from the chain")
        elif rid in good and good[rid].get("record_sha256") != sha:
            problems.append(f"record of run {rid}: sha256 {str(good[rid].get('record_sha256'))[:16]}... differs from "
                            f"records.parquet ({sha[:16]}...)")
    for rid, _ in expected_runs or []:
        if in_scope(rid) and rid not in records and rid not in listed:
            problems.append(f"run {rid} is in the archive but has no record")
    by_hash = {r.get("record_sha256"): rid for rid, r in good.items()}
    by_hash.update({sha: rid for rid, (sha, _) in listed.items() if sha not in by_hash})
    chain = sorted((rid for rid in good if in_scope(rid)), key=lambda rid: order[rid])
    for i, rid in enumerate(chain):
        got = good[rid]["content"].get("prev_record_sha256")
        want = good[chain[i - 1]].get("record_sha256") if i else None
        if got == want:
            continue
        prev_name = chain[i - 1] if i else None
        owner = by_hash.get(got)
        where = (f"which is the record of run {owner}" + (" (missing)" if owner not in good else "")) if owner \
            else "which matches no record"
        problems.append(
            f"chain link broken before run {rid}: its prev_record_sha256 is "
            f"{(got or 'null')[:16]}{'...' if got else ''}, {where}; the previous record present is "
            + (f"run {prev_name} with sha256 {str(want)[:16]}..." if prev_name else "none (it should be the first)"))
    return problems
