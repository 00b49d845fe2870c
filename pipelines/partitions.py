"""Partitions: one dynamic ``captures`` partition per captured run (``<device>__<run>``), one ``devices`` partition
per device. A device x run multi-partition would be a mostly empty cross product (docs/dagster.md 9.2)."""

import dagster as dg

SEP = "__"

captures = dg.DynamicPartitionsDefinition(name="captures")
devices = dg.DynamicPartitionsDefinition(name="devices")


def capture_key(device_id: str, run_id: str) -> str:
    return f"{device_id}{SEP}{run_id}"


def split_capture_key(key: str) -> tuple[str, str]:
    device_id, _, run_id = key.partition(SEP)
    if not run_id:
        raise ValueError(f"capture partition key {key!r} is not '<device>{SEP}<run>'")
    return device_id, run_id
