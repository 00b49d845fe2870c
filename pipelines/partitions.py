"""Partitions: one dynamic ``captures`` partition per captured run (``<device>__<run>``, ``assets_lib.store.keys``),
one ``devices`` partition per device. A device x run multi-partition would be a mostly empty cross product
(docs/dagster.md 9.2)."""

import dagster as dg

from assets_lib.store import split_capture_key

captures = dg.DynamicPartitionsDefinition(name="captures")
devices = dg.DynamicPartitionsDefinition(name="devices")


def registered_keys(instance: dg.DagsterInstance) -> tuple[list[str], list[str]]:
    """Capture and device partition keys registered on ``instance``, in partition order."""
    cap = list(instance.get_dynamic_partitions(captures.name))
    dev = list(instance.get_dynamic_partitions(devices.name))
    extra = sorted({split_capture_key(k)[0] for k in cap} - set(dev))
    return cap, dev + extra


def new_partition_requests(instance: dg.DagsterInstance, complete_keys) -> tuple[list[str], list]:
    """Capture keys among ``complete_keys`` not registered yet, and the dynamic-partition add requests that register
    them and their new devices (what the landing sensor returns and ``imulab run`` applies)."""
    known = set(instance.get_dynamic_partitions(captures.name))
    new = sorted(k for k in complete_keys if k not in known)
    requests = []
    if new:
        requests.append(captures.build_add_request(new))
        new_devices = sorted({split_capture_key(k)[0] for k in new} - set(instance.get_dynamic_partitions(devices.name)))
        if new_devices:
            requests.append(devices.build_add_request(new_devices))
    return new, requests
