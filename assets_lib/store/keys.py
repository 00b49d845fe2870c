"""Partition keys: one per captured run (``<device>__<run>``), one per device, one for the fleet."""

SEP = "__"
#: the single partition of fleet-level stages
FLEET_KEY = "fleet"


def capture_key(device_id: str, run_id: str) -> str:
    return f"{device_id}{SEP}{run_id}"


def split_capture_key(key: str) -> tuple[str, str]:
    device_id, _, run_id = key.partition(SEP)
    if not run_id:
        raise ValueError(f"capture partition key {key!r} is not '<device>{SEP}<run>'")
    return device_id, run_id
