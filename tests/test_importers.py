"""imulab import: every reader writes a run that ingest_run accepts, never touches its source, and names the
file / row / expectation on bad input."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from imulab.cli import main
from raw_schemas.errors import RawDataError
from raw_schemas.importers import RunMeta, import_run
from raw_schemas.readers import discover_runs, ingest_run


def _sha(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def _write_profile_case(tmp_path: Path, n=500, rate=200.0, with_error_row=None) -> tuple[Path, Path, np.ndarray]:
    rng = np.random.default_rng(1)
    counts = rng.integers(-3000, 3000, size=(n, 3))
    gyro_dps = rng.standard_normal((n, 3))
    df = pd.DataFrame({"stamp_ms": 1000.0 + np.arange(n) * 1000.0 / rate, "gx": gyro_dps[:, 0], "gy": gyro_dps[:, 1],
                       "gz": gyro_dps[:, 2], "ax": counts[:, 0], "ay": counts[:, 1], "az": counts[:, 2]})
    if with_error_row is not None:
        df["gy"] = df["gy"].astype(object)
        df.loc[with_error_row, "gy"] = "n/a"
    src = tmp_path / "log.csv"
    df.to_csv(src, index=False)
    prof = {"time": {"column": "stamp_ms", "unit": "ms"},
            "channels": {"gyro_x": {"column": "gy", "unit": "deg/s"},
                         "gyro_y": {"column": "gx", "unit": "deg/s", "sign": -1},
                         "gyro_z": {"column": "gz", "unit": "deg/s"},
                         "accel_x": {"column": "ay", "unit": "counts", "lsb": 0.5, "lsb_unit": "mg"},
                         "accel_y": {"column": "ax", "unit": "counts", "lsb": 0.5, "lsb_unit": "mg", "sign": -1},
                         "accel_z": {"column": "az", "unit": "counts", "lsb": 0.5, "lsb_unit": "mg"}}}
    pp = tmp_path / "profile.json"
    pp.write_text(json.dumps(prof))
    return src, pp, np.c_[gyro_dps, counts]


def test_profile_csv_axis_map_units_and_source_untouched(tmp_path):
    src, prof, raw = _write_profile_case(tmp_path)
    before = _sha(src)
    res = CliRunner().invoke(main, ["import", "profile", str(src), "--landing", str(tmp_path / "land"),
                                    "--device-id", "dev1", "--run-id", "r1", "-o", f"profile={prof}"])
    assert res.exit_code == 0, res.output
    assert _sha(src) == before
    run = ingest_run(tmp_path / "land" / "dev1" / "r1")
    imu = run.imu
    assert imu.time_s.iloc[0] == 0.0 and run.manifest.sample_rate_hz == pytest.approx(200.0)
    np.testing.assert_allclose(imu.gyro_x_radps, np.radians(raw[:, 1]), rtol=1e-12)
    np.testing.assert_allclose(imu.gyro_y_radps, -np.radians(raw[:, 0]), rtol=1e-12)
    np.testing.assert_allclose(imu.accel_y_mps2, -raw[:, 3] * 0.5e-3 * 9.80665, rtol=1e-12)
    assert discover_runs(tmp_path / "land") == [tmp_path / "land" / "dev1" / "r1"]
    # the landing area is append-only: a second import of the same run id is refused
    res2 = CliRunner().invoke(main, ["import", "profile", str(src), "--landing", str(tmp_path / "land"),
                                     "--device-id", "dev1", "--run-id", "r1", "-o", f"profile={prof}"])
    assert res2.exit_code == 2 and "exists already" in res2.output


def test_profile_bad_value_names_file_row_and_column(tmp_path):
    src, prof, _ = _write_profile_case(tmp_path, with_error_row=41)
    with pytest.raises(RawDataError) as e:
        import_run("profile", [src], tmp_path / "land", RunMeta("dev1", "r1"), {"profile": str(prof)})
    msg = str(e.value)
    assert "log.csv" in msg and "row 42 (line 43)" in msg and "'gy'" in msg and "finite number" in msg
    assert not (tmp_path / "land" / "dev1" / "r1").exists()


def test_profile_schema_file_matches_model():
    from raw_schemas.importers.profile import profile_json_schema

    committed = json.loads((Path(__file__).resolve().parents[1] / "raw_schemas" / "import_profile.schema.json").read_text())
    assert committed == profile_json_schema()


def test_profile_with_a_missing_channel_is_refused(tmp_path):
    src, prof, _ = _write_profile_case(tmp_path)
    p = json.loads(prof.read_text())
    del p["channels"]["gyro_z"]
    prof.write_text(json.dumps(p))
    with pytest.raises(RawDataError, match="profile.json.*gyro_z"):
        import_run("profile", [src], tmp_path / "land", RunMeta("dev1", "r1"), {"profile": str(prof)})


def _imu_msgs(n=400, rate=100.0):
    rng = np.random.default_rng(2)
    w = 0.01 * rng.standard_normal((n, 3))
    a = np.array([0.1, -0.2, 9.8]) + 0.02 * rng.standard_normal((n, 3))
    stamps = 1_700_000_000_000_000_000 + (np.arange(n) * 1e9 / rate).astype(np.int64)
    return stamps, w, a


def _ros_imu(store, ns, w, a, ros1=False):
    Imu = store.types["sensor_msgs/msg/Imu"]
    Header = store.types["std_msgs/msg/Header"]
    Time = store.types["builtin_interfaces/msg/Time"]
    V3 = store.types["geometry_msgs/msg/Vector3"]
    Q = store.types["geometry_msgs/msg/Quaternion"]
    cov = np.zeros(9)
    kw = {"seq": 0} if ros1 else {}
    return Imu(header=Header(stamp=Time(sec=int(ns // 1_000_000_000), nanosec=int(ns % 1_000_000_000)), frame_id="imu", **kw),
               orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0), orientation_covariance=cov,
               angular_velocity=V3(x=w[0], y=w[1], z=w[2]), angular_velocity_covariance=cov,
               linear_acceleration=V3(x=a[0], y=a[1], z=a[2]), linear_acceleration_covariance=cov)


@pytest.mark.parametrize("kind", ["ros2", "ros1", "mcap"])
def test_ros_sources_round_trip(tmp_path, kind):
    pytest.importorskip("rosbags")
    from rosbags.typesys import Stores, get_typestore

    stamps, w, a = _imu_msgs()
    if kind == "ros2":
        from rosbags.rosbag2 import Writer

        store = get_typestore(Stores.ROS2_HUMBLE)
        src = tmp_path / "bag2"
        with Writer(src, version=8) as wr:
            conn = wr.add_connection("/imu", "sensor_msgs/msg/Imu", typestore=store)
            other = wr.add_connection("/chatter", "std_msgs/msg/String", typestore=store)
            for i, ns in enumerate(stamps):
                wr.write(conn, int(ns), store.serialize_cdr(_ros_imu(store, ns, w[i], a[i]), "sensor_msgs/msg/Imu"))
            wr.write(other, int(stamps[0]), store.serialize_cdr(store.types["std_msgs/msg/String"](data="x"), "std_msgs/msg/String"))
    elif kind == "ros1":
        from rosbags.rosbag1 import Writer

        store = get_typestore(Stores.ROS1_NOETIC)
        src = tmp_path / "imu.bag"
        with Writer(src) as wr:
            conn = wr.add_connection("/imu", "sensor_msgs/msg/Imu", typestore=store)
            for i, ns in enumerate(stamps):
                wr.write(conn, int(ns), store.serialize_ros1(_ros_imu(store, ns, w[i], a[i], ros1=True), "sensor_msgs/msg/Imu"))
    else:
        pytest.importorskip("mcap")
        from mcap.writer import Writer
        store = get_typestore(Stores.ROS2_HUMBLE)
        src = tmp_path / "imu.mcap"
        msgdef, _ = store.generate_msgdef("sensor_msgs/msg/Imu", ros_version=2)
        with open(src, "wb") as f:
            wr = Writer(f)
            wr.start(profile="ros2", library="imulab-test")
            sid = wr.register_schema(name="sensor_msgs/msg/Imu", encoding="ros2msg", data=msgdef.encode())
            cid = wr.register_channel(topic="/imu", message_encoding="cdr", schema_id=sid)
            for i, ns in enumerate(stamps):
                wr.add_message(channel_id=cid, log_time=int(ns), publish_time=int(ns), sequence=i,
                               data=bytes(store.serialize_cdr(_ros_imu(store, ns, w[i], a[i]), "sensor_msgs/msg/Imu")))
            wr.finish()
    out = import_run("ros", [src], tmp_path / "land", RunMeta("dev", "r"), {})
    run = ingest_run(out)
    np.testing.assert_allclose(run.imu[["gyro_x_radps", "gyro_y_radps", "gyro_z_radps"]].to_numpy(), w, rtol=0, atol=0)
    np.testing.assert_allclose(run.imu[["accel_x_mps2", "accel_y_mps2", "accel_z_mps2"]].to_numpy(), a, rtol=0, atol=0)
    assert run.manifest.sample_rate_hz == pytest.approx(100.0)
    assert run.manifest.start_time_utc.year == 2023


def test_ros_unknown_topic_is_named(tmp_path):
    pytest.importorskip("rosbags")
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    stamps, w, a = _imu_msgs(10)
    with Writer(tmp_path / "b", version=8) as wr:
        conn = wr.add_connection("/imu", "sensor_msgs/msg/Imu", typestore=store)
        for i, ns in enumerate(stamps):
            wr.write(conn, int(ns), store.serialize_cdr(_ros_imu(store, ns, w[i], a[i]), "sensor_msgs/msg/Imu"))
    with pytest.raises(RawDataError, match="topic '/nope'.*/imu"):
        import_run("ros", [tmp_path / "b"], tmp_path / "land", RunMeta("dev", "r"), {"topic": "/nope"})
    # a value the option does not take is refused, not read as the default (header stamps)
    with pytest.raises(RawDataError, match=r"b, option 'time': expected 'record' or 'header'.*'recorded'"):
        import_run("ros", [tmp_path / "b"], tmp_path / "land", RunMeta("dev", "r"), {"time": "recorded"})
    assert not (tmp_path / "land").exists() or not any((tmp_path / "land").rglob("*.parquet"))


def test_imu_tk_mismatched_time_is_reported(tmp_path):
    acc = tmp_path / "acc.txt"
    gyr = tmp_path / "gyr.txt"
    t = np.arange(20) * 0.01
    np.savetxt(acc, np.c_[t, np.ones((20, 3))])
    t2 = t.copy()
    t2[7] += 0.001
    np.savetxt(gyr, np.c_[t2, np.ones((20, 3))])
    with pytest.raises(RawDataError, match=r"gyr.txt, data row 8: expected time"):
        import_run("imu_tk", [acc, gyr], tmp_path / "land", RunMeta("d", "r"), {"accel_lsb": "1", "gyro_lsb": "1"})
    bad = tmp_path / "bad.txt"
    bad.write_text("0 1 2 3\n0.01 1 2\n")
    with pytest.raises(RawDataError, match=r"bad.txt, line 2: expected 4 numbers per line, found 3"):
        import_run("imu_tk", [bad, gyr], tmp_path / "land", RunMeta("d", "r"), {})


def _imu_tk_offset_files(tmp_path: Path, zero=32768, acc_lsb=0.0024, gyro_lsb=0.00021):
    """A tiny imu_tk session in unsigned counts: 3 static poses (gravity along +z, -x, +y) and a 0.5 rad/s turn,
    written as ``zero + round(value / lsb)``; returns the files and the values the counts stand for."""
    n = 60
    t = 0.01 * np.arange(1, 3 * n + 1)
    f = np.repeat([[0.0, 0.0, 9.81], [-9.81, 0.0, 0.0], [0.0, 9.81, 0.0]], n, axis=0)
    w = np.zeros_like(f)
    w[n:2 * n, 1] = 0.5
    acc_counts, gyro_counts = np.round(f / acc_lsb), np.round(w / gyro_lsb)
    acc, gyr = tmp_path / "acc.txt", tmp_path / "gyro.txt"
    np.savetxt(acc, np.c_[t, zero + acc_counts], fmt=["%.2f", "%d", "%d", "%d"])
    np.savetxt(gyr, np.c_[t, zero + gyro_counts], fmt=["%.2f", "%d", "%d", "%d"])
    return acc, gyr, acc_counts * acc_lsb, gyro_counts * gyro_lsb


def test_imu_tk_zero_count_is_removed_before_scaling(tmp_path):
    import warnings

    from raw_schemas.importers import ImportedDataWarning

    acc, gyr, f_si, w_si = _imu_tk_offset_files(tmp_path)
    opts = {"accel_lsb": "0.0024", "gyro_lsb": "0.00021", "accel_zero_count": "32768", "gyro_zero_count": "32768"}
    with warnings.catch_warnings():
        warnings.simplefilter("error", ImportedDataWarning)  # the right zero and lsb: no warning
        run = ingest_run(import_run("imu_tk", [acc, gyr], tmp_path / "land", RunMeta("d", "zeroed"), opts))
    np.testing.assert_allclose(run.imu[["accel_x_mps2", "accel_y_mps2", "accel_z_mps2"]].to_numpy(), f_si, rtol=0, atol=1e-12)
    np.testing.assert_allclose(run.imu[["gyro_x_radps", "gyro_y_radps", "gyro_z_radps"]].to_numpy(), w_si, rtol=0, atol=1e-12)
    mag = np.linalg.norm(run.imu[["accel_x_mps2", "accel_y_mps2", "accel_z_mps2"]].to_numpy(), axis=1)
    assert np.all(np.abs(mag - 9.81) < 0.0024)  # 1 g within one count
    assert "accel zero count 32768 subtracted" in run.manifest.notes

    # the same counts without the zero: written (counts are counts) but the import says what is wrong, naming the file
    with pytest.warns(ImportedDataWarning) as rec:
        import_run("imu_tk", [acc, gyr], tmp_path / "land", RunMeta("d", "raw"), {"accel_lsb": "0.0024", "gyro_lsb": "0.00021"})
    msgs = [str(w.message) for w in rec if issubclass(w.category, ImportedDataWarning)]
    acc_msg = next(m for m in msgs if m.startswith("acc.txt:"))
    med = float(np.median(np.linalg.norm(np.loadtxt(acc)[:, 1:] * 0.0024, axis=1)))  # what the run now holds
    assert 10 < med / 9.80665 < 20  # ~14 g: the mid-scale offset, not gravity
    assert f"median specific force |f| of the record is {med:.4g} m/s^2 ({med / 9.80665:.3g} g)" in acc_msg
    assert "-o accel_zero_count=N" in acc_msg
    gyro_msg = next(m for m in msgs if m.startswith("gyro.txt:"))
    assert "median angular rate" in gyro_msg and "gyro_zero_count" in gyro_msg

    # a wrong lsb with the right zero is caught too (the lsb declared in g: 9.81 g), and a zero count on physical
    # values is refused
    with pytest.warns(ImportedDataWarning, match=r"acc.txt: .*\(9.81 g\).*accel_lsb \(given 0.0024 g\)"):
        import_run("imu_tk", [acc, gyr], tmp_path / "land", RunMeta("d", "badlsb"), {**opts, "accel_lsb_unit": "g"})
    phys = tmp_path / "phys.txt"
    np.savetxt(phys, np.c_[0.01 * np.arange(1, 181), np.tile([0.1, 0.2, 9.8], (180, 1))], fmt="%.3f")
    with pytest.raises(RawDataError, match=r"phys.txt, option 'accel_zero_count': expected integer counts"):
        import_run("imu_tk", [phys, gyr], tmp_path / "land", RunMeta("d", "phys"), opts)


def test_cli_import_imu_tk_warns_on_offset_counts(tmp_path):
    acc, gyr, _, _ = _imu_tk_offset_files(tmp_path)
    args = ["import", "imu_tk", str(acc), str(gyr), "--landing", str(tmp_path / "land"), "--device-id", "d",
            "-o", "accel_lsb=0.0024", "-o", "gyro_lsb=0.00021"]
    r = CliRunner().invoke(main, [*args, "--run-id", "raw"])
    assert r.exit_code == 0, r.output
    assert "WARN import imu_tk: acc.txt: the median specific force |f| of the record is" in r.output
    assert "WARN import imu_tk: gyro.txt: the median angular rate |w| of the record is" in r.output
    assert "-o accel_zero_count=N" in r.output
    r = CliRunner().invoke(main, [*args, "--run-id", "zeroed", "-o", "accel_zero_count=32768", "-o", "gyro_zero_count=32768"])
    assert r.exit_code == 0 and "WARN" not in r.output, r.output


def test_imucal_session_import(shared_data, tmp_path):
    src = shared_data / "imucal_example" / "annotated_session.csv"
    before = _sha(src)
    out = import_run("imucal", [src], tmp_path / "land", RunMeta("bmi160", "ferraris1"),
                     {"sample_rate_hz": "204.8", "accel_lsb": str(1 / 2048), "gyro_lsb": str(1 / 16.4)})
    assert _sha(src) == before
    run = ingest_run(out)
    steps = run.manifest.plan.steps
    assert [s.label for s in steps] == ["x_p", "x_a", "y_p", "y_a", "z_p", "z_a", "x_rot", "y_rot", "z_rot"]
    assert steps[0].up_axis_body == "+x" and steps[1].up_axis_body == "-x"
    assert steps[6].rotation_axis_body == "x" and steps[6].rotation_angle_deg == -360.0
    assert len(run.imu) == 9414


def test_profile_parquet_with_rate_and_tablefree_kind(tmp_path):
    rng = np.random.default_rng(5)
    n = 300
    df = pd.DataFrame({c: rng.standard_normal(n) for c in ("wx", "wy", "wz", "fx", "fy", "fz")})
    src = tmp_path / "log.parquet"
    df.to_parquet(src)
    prof = {"time": {"rate_hz": 50.0}, "test_kind": "tablefree",
            "channels": {**{f"gyro_{a}": {"column": f"w{a}", "unit": "rad/s"} for a in "xyz"},
                         **{f"accel_{a}": {"column": f"f{a}", "unit": "g"} for a in "xyz"}}}
    (tmp_path / "p.json").write_text(json.dumps(prof))
    run = ingest_run(import_run("profile", [src], tmp_path / "land", RunMeta("d", "r"), {"profile": str(tmp_path / "p.json")}))
    assert run.manifest.test_kind == "tablefree" and run.manifest.plan.steps[0].kind == "free"
    assert run.manifest.sample_rate_hz == 50.0
    np.testing.assert_allclose(run.imu.accel_z_mps2, df.fz * 9.80665, rtol=1e-12)


def test_cli_import_imu_tk_writes_a_run(shared_data, tmp_path):
    d = shared_data / "imu_tk_xsens"
    r = CliRunner().invoke(main, ["import", "imu_tk", str(d / "xsens_acc.mat"), str(d / "xsens_gyro.mat"),
                                  "--landing", str(tmp_path), "--device-id", "xsens", "--run-id", "demo",
                                  "--gravity-mps2", "9.81744", "-o", "accel_lsb=0.0024", "-o", "gyro_lsb=0.00016",
                                  "-o", "initial_static_s=50"])
    assert r.exit_code == 0, r.output
    run = ingest_run(tmp_path / "xsens" / "demo")
    steps = run.manifest.plan.steps
    assert [s.kind for s in steps] == ["pose", "free"] and steps[0].end_s == pytest.approx(50.0)
    assert run.manifest.site.gravity_mps2 == 9.81744
    assert run.imu.time_s.iloc[0] == pytest.approx(0.02984)  # the IMU clock is kept


# ------------------------------------------------------------------------------------------------------------------
# -o options: every importer declares the keys it reads (OPTIONS); any other key is refused before anything is read
# ------------------------------------------------------------------------------------------------------------------
def test_unknown_option_is_refused_naming_key_format_and_suggestion(tmp_path):
    from raw_schemas.importers import accepted_options

    acc, gyr, _, _ = _imu_tk_offset_files(tmp_path)
    opts = {"acel_lsb": "0.0024", "gyro_lsb": "0.00021", "accel_zero_count": "32768", "gyro_zero_count": "32768"}
    with pytest.raises(RawDataError) as e:
        import_run("imu_tk", [acc, gyr], tmp_path / "land", RunMeta("d", "r"), opts)
    msg = str(e.value)
    assert "option 'acel_lsb'" in msg and "format 'imu_tk'" in msg and "did you mean 'accel_lsb'?" in msg, msg
    assert str(sorted(accepted_options("imu_tk"))) in msg, msg  # the accepted options, sorted
    assert not (tmp_path / "land").exists()  # refused before anything is written

    # a key of another format: named, with the format that takes it; several unknown keys are all named
    with pytest.raises(RawDataError, match=r"options 'gyro_zero_count', 'bogus'.*format 'imucal'.*"
                                           r"'gyro_zero_count' \(.*accepted by format 'imu_tk'\), 'bogus'"):
        import_run("imucal", [acc], tmp_path / "land", RunMeta("d", "r"),
                   {"sample_rate_hz": "100", "gyro_zero_count": "32768", "bogus": "1"})
    # site metadata given as a format option: pointed to the command-line option
    with pytest.raises(RawDataError, match=r"'gravity_mps2' \(run metadata, not a format option: "
                                           r"RunMeta\(gravity_mps2=\.\.\.\), imulab import --gravity-mps2\)"):
        import_run("imu_tk", [acc, gyr], tmp_path / "land", RunMeta("d", "r"), {"gravity_mps2": "9.81"})
    # with the right key the same import goes through
    opts["accel_lsb"] = opts.pop("acel_lsb")
    import_run("imu_tk", [acc, gyr], tmp_path / "land", RunMeta("d", "r"), opts)


def test_cli_unknown_option_exits_2_with_the_message_on_stderr(tmp_path):
    acc, gyr, _, _ = _imu_tk_offset_files(tmp_path)
    r = CliRunner().invoke(main, ["import", "imu_tk", str(acc), str(gyr), "--landing", str(tmp_path / "land"),
                                  "--device-id", "d", "-o", "accel_lsb=0.0024", "-o", "gyro_lsb=0.00021",
                                  "-o", "accel_zero_count=32768", "-o", "gyro_zero_count=32768", "-o", "acel_lsb_unit=g"])
    assert r.exit_code == 2, r.output
    assert r.stderr.startswith("FAIL import imu_tk: (options), option 'acel_lsb_unit'"), r.stderr
    assert "did you mean 'accel_lsb_unit'?" in r.stderr and "format 'imu_tk'" in r.stderr
    assert "ok " not in r.stdout and not (tmp_path / "land").exists()


def test_help_lists_each_formats_declared_options():
    import importlib

    from raw_schemas.importers import IMPORTERS

    r = CliRunner().invoke(main, ["import", "--help"])
    assert r.exit_code == 0, r.output
    lines = r.output.splitlines()
    for fmt, (mod, _) in IMPORTERS.items():
        opts = importlib.import_module(mod).OPTIONS
        assert opts and all(isinstance(k, str) and isinstance(d, str) and d for k, d in opts.items())
        i = next(k for k, ln in enumerate(lines) if ln.strip().startswith(f"{fmt}:"))
        listed = []
        for ln in lines[i + 1:]:
            if not ln.startswith("      "):
                break
            listed.append(ln.split()[0])
        assert listed == sorted(opts), (fmt, listed)


class _Spy(dict):
    """Options dict that records every key an importer looks up."""

    def __init__(self, *a, **k):
        super().__init__(*a, **k)
        self.seen = set()

    def get(self, key, default=None):
        self.seen.add(key)
        return super().get(key, default)

    def __getitem__(self, key):
        self.seen.add(key)
        return super().__getitem__(key)

    def __contains__(self, key):
        self.seen.add(key)
        return super().__contains__(key)


def test_declared_options_are_the_keys_the_importers_read(tmp_path):
    """Every key a reader looks up is declared in its OPTIONS (a key read but not declared would be refused)."""
    from raw_schemas.importers import accepted_options, imu_tk, imucal, profile

    seen = {}
    acc, gyr, _, _ = _imu_tk_offset_files(tmp_path)
    o = _Spy(accel_lsb="0.0024", gyro_lsb="0.00021", accel_zero_count="32768", gyro_zero_count="32768",
             initial_static_s="0.5")
    imu_tk.read([acc, gyr], o)
    phys = tmp_path / "phys.txt"
    np.savetxt(phys, np.c_[0.01 * np.arange(1, 181), np.tile([0.1, 0.2, 9.8], (180, 1))], fmt="%.3f")
    o2 = _Spy()
    imu_tk.read([phys, phys], o2)
    seen["imu_tk"] = o.seen | o2.seen

    rng = np.random.default_rng(0)
    rows = [(p, 50) for p in imucal.SECTIONS]
    part = np.concatenate([[p] * n for p, n in rows])
    df = pd.DataFrame({"part": part, "samples": np.arange(part.size),
                       **{c: rng.standard_normal(part.size) for c in imucal.DATA_COLUMNS}})
    df.to_csv(tmp_path / "s.csv", index=False)
    o = _Spy(sample_rate_hz="100")
    imucal.read([tmp_path / "s.csv"], o)
    cont = df.drop(columns="part")
    cont[list(imucal.DATA_COLUMNS)] = cont[list(imucal.DATA_COLUMNS)].round()  # integer counts: the lsb path
    cont.to_csv(tmp_path / "c.csv", index=False)
    (tmp_path / "sec.json").write_text(json.dumps({p: {"start": 50 * i, "end": 50 * (i + 1)}
                                                   for i, p in enumerate(imucal.SECTIONS)}))
    o2 = _Spy(sample_rate_hz="100", sections=str(tmp_path / "sec.json"), accel_lsb="0.001", gyro_lsb="0.1")
    imucal.read([tmp_path / "c.csv"], o2)
    seen["imucal"] = o.seen | o2.seen

    src, prof, _ = _write_profile_case(tmp_path)
    o = _Spy(profile=str(prof))
    profile.read([src], o)
    seen["profile"] = o.seen
    for fmt, keys in seen.items():
        assert keys <= set(accepted_options(fmt)), (fmt, sorted(keys - set(accepted_options(fmt))))
    assert seen["imu_tk"] == set(accepted_options("imu_tk"))  # both paths together read every declared key
    assert seen["imucal"] == set(accepted_options("imucal"))


def test_ros_declared_options_match_the_source():
    """The ros reader's option lookups (it needs bag files to run): every literal key it reads is declared."""
    import re

    from raw_schemas.importers import accepted_options, ros

    src = Path(ros.__file__).read_text()
    keys = set(re.findall(r"options\.get\(\"(\w+)\"", src)) | set(re.findall(r"options\[\"(\w+)\"\]", src))
    assert keys == set(accepted_options("ros")), keys


def _realdata_import_options() -> list[tuple[str, str]]:
    """(format, key) of every ``-o key=`` in the ``imulab import FORMAT`` commands of docs/realdata.md (continuation
    lines joined), and (None, key) for every other ``-o key=`` the page names."""
    import re
    import shlex

    text = (Path(__file__).resolve().parents[1] / "docs" / "realdata.md").read_text()
    lines, out, in_cmd = text.splitlines(), [], set()
    i = 0
    while i < len(lines):
        if lines[i].strip().startswith("imulab import ") and "FORMAT" not in lines[i]:
            start, cmd = i, lines[i].strip()
            while cmd.endswith("\\"):
                i += 1
                cmd = cmd[:-1] + " " + lines[i].strip()
            in_cmd.update(range(start, i + 1))
            args = shlex.split(cmd)
            out += [(args[2], args[k + 1].split("=", 1)[0]) for k, a in enumerate(args) if a in ("-o", "--option")]
        i += 1
    for k, ln in enumerate(lines):
        if k not in in_cmd:
            out += [(None, m) for m in re.findall(r"-o ([a-z][a-z0-9_]*)=", ln)]
    return out


def test_every_option_in_docs_realdata_is_accepted():
    from raw_schemas.importers import IMPORTERS, accepted_options

    used = _realdata_import_options()
    assert sum(f is not None for f, _ in used) >= 8, used  # the sec. 5 commands are found
    for fmt, key in used:
        if fmt is not None:
            assert key in accepted_options(fmt), f"docs/realdata.md: imulab import {fmt} -o {key}= is not accepted"
        else:
            assert any(key in accepted_options(f) for f in IMPORTERS), f"docs/realdata.md: -o {key}= is no format's option"
