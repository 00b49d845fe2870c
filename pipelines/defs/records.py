"""Checks of the records stages (``assets_lib.stages.records``): a blocking check verifies every device's record
chain after every materialization; another checks that every certificate shows exactly its current record."""

import dagster as dg

from assets_lib.records import certificate_problems, chain_problems, load_records_dir
from pipelines.partitions import devices
from pipelines.resources import ParquetStore


@dg.asset_check(asset="calibration_record", name="record_chain_intact", blocking=True, partitions_def=devices,
                description="Every record's hash matches its content, every link matches the previous record, and "
                            "every ingested run the version was built from has its record.")
def record_chain_intact(context: dg.AssetCheckExecutionContext, store: ParquetStore) -> dg.AssetCheckResult:
    st = store.store
    keys = context.partition_keys if context.has_partition_key_range or context.has_partition_key \
        else st.partitions("calibration_record")
    problems, checked = [], 0
    for dev in keys:
        version = st.current_version("calibration_record", dev)
        if version is None:
            continue
        vdir = st.version_dir("calibration_record", dev, version)
        recs, listing = load_records_dir(vdir)
        meta = st.read_meta("calibration_record", dev, version)
        expected = []
        for k, v in (meta.get("inputs") or {}).items():
            asset, _, part = k.partition("/")
            if asset == "ingested_run":
                m = st.read_meta("ingested_run", part, v)
                expected.append((m["run_id"], m["start_time_utc"]))
        problems += [f"{dev}: {p}" for p in chain_problems(recs, listing, expected)]
        checked += len(recs)
    return dg.AssetCheckResult(
        passed=not problems,
        severity=dg.AssetCheckSeverity.ERROR,
        metadata={"records_checked": checked, "problems": "\n".join(problems) or "none"},
        description="; ".join(problems)[:2000] or None,
    )


@dg.asset_check(asset="certificate", name="certificates_show_their_records", partitions_def=devices,
                description="Every certificate of the device's current certificate version was rendered from the "
                            "current record version, embeds its record unedited and shows exactly its values "
                            "(assets_lib.records.certificate.certificate_problems).")
def certificates_show_their_records(context: dg.AssetCheckExecutionContext, store: ParquetStore
                                    ) -> dg.AssetCheckResult:
    st = store.store
    problems, checked = [], 0
    for dev in context.partition_keys:
        version = st.current_version("certificate", dev)
        if version is None:
            continue
        rec_version = st.current_version("calibration_record", dev)
        if st.read_meta("certificate", dev, version).get("record_version") != rec_version:
            problems.append(f"{dev}: certificates rendered from another record version than the current one")
        records, _ = load_records_dir(st.version_dir("calibration_record", dev, rec_version))
        for page in sorted(st.version_dir("certificate", dev, version).glob("*.html")):
            rec, probs = certificate_problems(page.read_text(encoding="utf-8"))
            if rec is not None and records.get(page.stem, {}).get("record_sha256") != rec.get("record_sha256"):
                probs = [*probs, "its record is not the stored record of the run"]
            problems += [f"{dev}/{page.name}: {x}" for x in probs]
            checked += 1
    return dg.AssetCheckResult(
        passed=not problems,
        severity=dg.AssetCheckSeverity.ERROR,
        metadata={"certificates_checked": checked, "problems": "\n".join(problems) or "none"},
        description="; ".join(problems)[:2000] or None,
    )


CHECKS = [record_chain_intact, certificates_show_their_records]
