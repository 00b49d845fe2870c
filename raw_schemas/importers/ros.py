"""``sensor_msgs/Imu`` messages from ROS 1 bags (``.bag``), ROS 2 bag folders (sqlite3 or mcap storage) and bare
MCAP files, read with the ``rosbags`` and ``mcap`` libraries (optional extra ``imulab[ros]``).

``angular_velocity`` (rad/s) and ``linear_acceleration`` (m/s^2) become the contract channels, the message
header stamp becomes ``time_s`` (seconds from the first message; the first stamp becomes ``start_time_utc``).
A message with a zero header stamp is timed by its record time instead (option ``time=record`` forces that).
Options: ``topic`` (needed when the source holds more than one Imu topic), ``test_kind`` (``static``, default,
or ``tablefree``).
"""

from __future__ import annotations

from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pandas as pd

from raw_schemas.errors import RawDataError
from raw_schemas.importers.common import ImportedSession, median_rate_hz, sha256_sources, whole_session_steps

IMU_TYPES = ("sensor_msgs/msg/Imu", "sensor_msgs/Imu")

#: the ``-o KEY=VALUE`` options this importer reads (key -> one-line description); any other key is refused
OPTIONS = {
    "topic": "the sensor_msgs/Imu topic (needed when the source holds several)",
    "time": "'record': time messages by their record time, not the header stamp ('header', the default)",
    "test_kind": "'static' (default) or 'tablefree'",
}


def _need(pkg: str):
    try:
        return __import__(pkg)
    except ImportError:
        raise RawDataError("(importer ros)", f"package {pkg!r}", "the optional dependency: pip install 'imulab[ros]'",
                           "not installed") from None


def _pick_topic(found: dict, options: dict, name: str) -> str:
    imu_topics = sorted(t for t, ty in found.items() if ty in IMU_TYPES)
    topic = options.get("topic")
    if topic is not None:
        if topic not in found:
            raise RawDataError(name, f"topic {topic!r}", f"a topic of the source {sorted(found)}", "no such topic")
        if found[topic] not in IMU_TYPES:
            raise RawDataError(name, f"topic {topic!r}", "sensor_msgs/Imu messages", found[topic])
        return topic
    if len(imu_topics) != 1:
        raise RawDataError(name, "topics", "exactly one sensor_msgs/Imu topic, or -o topic=NAME",
                           f"{imu_topics or 'none'} (all topics: {sorted(found)})")
    return imu_topics[0]


def _rows_from_msgs(items, name: str, use_record_time: bool):
    """items: iterable of (record_time_ns, msg). Returns (stamp_ns array, 6 x n values)."""
    stamps, vals = [], []
    for i, (rec_ns, msg) in enumerate(items):
        st = msg.header.stamp
        ns = int(st.sec) * 1_000_000_000 + int(st.nanosec if hasattr(st, "nanosec") else st.nsec)
        if use_record_time or ns == 0:
            ns = int(rec_ns)
        w, a = msg.angular_velocity, msg.linear_acceleration
        row = (w.x, w.y, w.z, a.x, a.y, a.z)
        if not all(np.isfinite(row)):
            raise RawDataError(name, f"message {i + 1}", "finite angular_velocity and linear_acceleration", repr(row))
        stamps.append(ns)
        vals.append(row)
    if len(stamps) < 2:
        raise RawDataError(name, "messages", "at least two sensor_msgs/Imu messages", f"{len(stamps)}")
    return np.asarray(stamps, dtype=np.int64), np.asarray(vals, dtype=float)


def _read_rosbags(path: Path, options: dict):
    _need("rosbags")
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    try:
        with AnyReader([path], default_typestore=store) as reader:
            found = {c.topic: c.msgtype for c in reader.connections}
            topic = _pick_topic(found, options, path.name)
            conns = [c for c in reader.connections if c.topic == topic]
            items = ((ts, reader.deserialize(raw, conn.msgtype)) for conn, ts, raw in reader.messages(connections=conns))
            return topic, _rows_from_msgs(items, path.name, options.get("time") == "record")
    except RawDataError:
        raise
    except Exception as e:  # the library's own reader errors: name the file
        raise RawDataError(path.name, "file", "a readable ROS 1 bag or ROS 2 bag folder", f"{type(e).__name__}: {e}") from None


def _read_mcap(path: Path, options: dict):
    _need("mcap")
    _need("rosbags")
    from mcap.reader import make_reader
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    try:
        with open(path, "rb") as f:
            reader = make_reader(f)
            summary = reader.get_summary()
            if summary is None:
                raise RawDataError(path.name, "file", "an MCAP file with a summary section", "none (file cut?)")
            found = {}
            for ch in summary.channels.values():
                sch = summary.schemas.get(ch.schema_id)
                found[ch.topic] = sch.name if sch else ""
            topic = _pick_topic(found, options, path.name)
            for ch in summary.channels.values():
                if ch.topic == topic:
                    sch = summary.schemas[ch.schema_id]
                    if ch.message_encoding != "cdr":
                        raise RawDataError(path.name, f"topic {topic!r}", "CDR-encoded (ROS 2) messages", ch.message_encoding)
                    if sch.encoding == "ros2msg" and sch.name not in store.types:
                        store.register(get_types_from_msg(sch.data.decode(), sch.name))
            f.seek(0)
            reader = make_reader(f)
            items = ((m.log_time, store.deserialize_cdr(m.data, "sensor_msgs/msg/Imu"))
                     for _, _, m in reader.iter_messages(topics=[topic]))
            return topic, _rows_from_msgs(items, path.name, options.get("time") == "record")
    except RawDataError:
        raise
    except Exception as e:
        raise RawDataError(path.name, "file", "a readable MCAP file", f"{type(e).__name__}: {e}") from None


def read(sources: list[Path], options: dict) -> ImportedSession:
    if len(sources) != 1:
        raise RawDataError("(sources)", "command line", "one bag file, bag folder or MCAP file", f"{len(sources)}")
    path = sources[0]
    if options.get("time", "header") not in ("header", "record"):
        raise RawDataError(path.name, "option 'time'", "'record' or 'header'", repr(options["time"]))
    if not path.exists():
        raise RawDataError(str(path), "", "an existing bag file, bag folder or MCAP file", "no such file")
    if path.is_file() and path.suffix == ".mcap":
        topic, (ns, v) = _read_mcap(path, options)
    else:
        topic, (ns, v) = _read_rosbags(path, options)
    order = np.argsort(ns, kind="stable")
    if np.any(order != np.arange(ns.size)):
        i = int(np.flatnonzero(np.diff(ns) < 0)[0]) + 1
        raise RawDataError(path.name, f"topic {topic!r}, message {i + 1}", "header stamps in increasing order",
                           "a stamp earlier than the previous message")
    t = (ns - ns[0]) * 1e-9
    rate = median_rate_hz(t, path.name)
    start = datetime.fromtimestamp(ns[0] // 1_000_000_000, tz=timezone.utc).replace(microsecond=(ns[0] % 1_000_000_000) // 1000)
    imu = pd.DataFrame({"time_s": t, "gyro_x": v[:, 0], "gyro_y": v[:, 1], "gyro_z": v[:, 2],
                        "accel_x": v[:, 3], "accel_y": v[:, 4], "accel_z": v[:, 5]})
    channels = {**{f"gyro_{a}": {"unit": "rad/s"} for a in "xyz"}, **{f"accel_{a}": {"unit": "m/s^2"} for a in "xyz"}}
    kind = options.get("test_kind", "static")
    if kind == "tablefree":
        steps = whole_session_steps(t, rate)
    elif kind == "static":
        steps = [{"index": 0, "kind": "static", "start_s": 0.0, "duration_s": float(t[-1]) or 1.0 / rate,
                  "orientation_b2l": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "label": "static record (orientation unknown)"}]
    else:
        raise RawDataError(path.name, "option 'test_kind'", "'static' or 'tablefree'", repr(kind))
    return ImportedSession(
        imu=imu, channels=channels, sample_rate_hz=rate, test_kind=kind, steps=steps, plan_name=f"ROS topic {topic}",
        notes=f"imported from {path.name}, topic {topic}", start_time_utc=start.isoformat().replace("+00:00", "Z"),
        sources=sha256_sources([path]),
    )
