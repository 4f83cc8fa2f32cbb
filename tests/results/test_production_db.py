"""One database for many stations: the history on SQLite and on a real PostgreSQL server
(tests/pgserver.py: Debian's postgresql, started here as the unprivileged postgres user on a
loopback port), the production record, concurrent writers in separate processes, migrations
of a schema-1 file made by the previous imubench, the production queries and the export."""
from __future__ import annotations

import hashlib
import json
import multiprocessing as mp
import shutil
import sqlite3
import time
import uuid
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
from dbwriters import production_result, reader, writer
from imubench.cli import main as imubench
from imubench.results import db as DB
from imubench.results import history as H
from imubench.results.export import junit_xml, measurements_of, session_dict
from imubench.results.history import History, SchemaError
from pgserver import PgServer

DATA = Path(__file__).resolve().parents[1] / "data"
V1_FILE = DATA / "history-v1.sqlite"     # written by imubench at commit cdd83b2 (history schema 1)
UID_A = "0123456789ABCDEF01234567"
UID_B = "0123FFFF89ABCDEF01234567"
UID_C = "FEDCBA9876543210FEDCBA98"


@pytest.fixture(scope="session")
def pg():
    """A PostgreSQL server for the whole test session; failing to start it fails the tests."""
    server = PgServer()
    try:
        server.start()
    except BaseException:
        server.stop()
        raise
    yield server
    server.stop()


@pytest.fixture(params=["sqlite", "postgresql"])
def target(request, tmp_path):
    if request.param == "sqlite":
        return str(tmp_path / "line.sqlite")
    return request.getfixturevalue("pg").createdb("t_" + uuid.uuid4().hex[:12])


def test_the_server_is_debians_and_runs_unprivileged(pg):
    assert str(pg.bindir).startswith("/usr/lib/postgresql/")
    with History(pg.createdb("who")) as h:
        with h._read() as db:
            assert db.exec_driver_sql("SHOW port").scalar() == str(pg.port)
            assert db.exec_driver_sql("SELECT inet_server_addr()::text").scalar() == "127.0.0.1/32"
        assert h.dialect == "postgresql"
    owner = pg.data.stat().st_uid
    import os
    import pwd
    assert pwd.getpwuid(owner).pw_name == ("postgres" if os.geteuid() == 0 else pwd.getpwuid(os.geteuid()).pw_name)


def test_production_record_round_trip(target):
    r = production_result(UID_A, "2026-11-22T06:40:00+00:00", station="S7", slot=3)
    with History(target) as h:
        rid = h.record(r)
        assert h.record(json.loads(json.dumps(r))) == rid           # the same record again: one run
        got = h.run(rid)
        (dev,) = h.devices()
    assert got["record"] == r
    assert (got["station_id"], got["operator"], got["fixture"], got["slot"]) == ("S7", "ana", "plate-4", 3)
    assert got["host_version"] == "0.1.0" and got["fw_version"] == "0.2.0" and got["fw_build"] == "sim-0.1.0"
    assert got["params_before"] == {"cal_id": 0} and got["params_after"] == {"cal_id": 0}
    assert got["capture_sha256"] == "0" * 64 and got["capture_uri"].startswith("file:///data/S7/")
    assert [m["name"] for m in got["measurements"]] == [m["name"] for m in measurements_of(r)]
    acc = got["measurements"][0]
    assert acc == {"name": "accel_norm_rms_mg", "value": 0.01, "unit": "mg", "low": None, "high": 1.0, "passed": True}
    assert dev["mcu_uid"] == UID_A and dev["runs"] == 1


def test_a_failed_board_without_fit_or_identity_is_recorded_with_its_reason(target):
    failed = {"schema": 2, "device": {"mcu_uid": None}, "started": "2026-11-22T07:00:00+00:00",
              "finished": "2026-11-22T07:00:30+00:00", "passed": False, "written": False, "verified": False,
              "failure": {"stage": "link", "reason": "no answer from the device"},
              "station": {"id": "S1", "slot": 4, "port": "socket://127.0.0.1:9"}, "session_id": "sess-1"}
    faulted = production_result(UID_B, "2026-11-22T07:00:00+00:00", slot=2, passed=False) | {
        "accel": None, "gyro": None, "poses": [], "method": "six", "written": False, "verified": False,
        "failure": {"stage": "health", "reason": "refusing to calibrate on faulted data: gyro Y fault bits"}}
    with History(target) as h:
        a = h.record(failed)
        assert h.record(failed) == a                                  # idempotent without a UID too
        h.record(faulted)
        h.record(production_result(UID_C, "2026-11-22T07:00:00+00:00", slot=1))
        fails = h.failures()
    assert [(f["slot"], f["failed_stage"]) for f in fails] == [(2, "health"), (4, "link")]   # newest first
    assert fails[1]["mcu_uid"] is None and fails[1]["failure"] == "no answer from the device"
    assert "gyro Y fault bits" in fails[0]["failure"]


def test_an_incomplete_failure_record_is_refused(target):
    bad = {"schema": 2, "device": {}, "started": "2026-11-22T07:00:00+00:00", "finished": "2026-11-22T07:00:00+00:00",
           "passed": True, "failure": {"stage": "link"}}
    with History(target) as h:
        with pytest.raises(ValueError, match="stage and reason.*cannot have passed"):
            h.record(bad)
        assert h.count_runs() == 0


def test_concurrent_writers_in_processes_lose_nothing_and_never_interleave(target):
    """Four station processes record at the same time (a third of their runs on one shared
    device), while a fifth process reads: every run arrives, each with its own record and
    all its measurements, and the reader never sees half a run."""
    n_writers, n = 4, 24
    ctx = mp.get_context("spawn")
    with History(target):                       # created before: the race is about records, not DDL
        pass
    expected = len(measurements_of(production_result(UID_A, "2026-11-20T08:00:00+00:00")))
    barrier = ctx.Barrier(n_writers)
    q = ctx.Queue()
    rd = ctx.Process(target=reader, args=(target, time.monotonic() + 6.0, expected, q))
    rd.start()
    procs = [ctx.Process(target=writer, args=(target, w, n, barrier, UID_A)) for w in range(n_writers)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(120)
    assert [p.exitcode for p in procs] == [0] * n_writers
    rd.join(60)
    seen = q.get(timeout=10)
    assert seen["bad"] == [] and seen["polls"] > 5, seen
    with History(target, readonly=True) as h:
        assert h.count_runs() == n_writers * n
        shared = h.runs(UID_A)
        assert len(shared) == n_writers * ((n + 2) // 3)
        for w in range(n_writers):
            for k in range(n):
                uid = UID_A if k % 3 == 0 else f"{w:04X}{k:020X}"
                if uid != UID_A:
                    (run,) = h.runs(uid)
                    assert run["note"] == f"writer {w} record {k}" and run["station_id"] == f"S{w}"
                    assert run["record"]["note"] == run["note"]                 # the row and its record agree
                    assert len(run["measurements"]) == expected
        dev = next(d for d in h.devices() if d["mcu_uid"] == UID_A)
        assert dev["runs"] == len(shared)
        assert dev["first_seen"] == min(r["started_utc"] for r in shared)
        assert dev["last_seen"] == max(r["started_utc"] for r in shared)


# ------------------------------------------------------------------ migrations
def test_a_schema_1_file_is_upgraded_in_place(tmp_path):
    db = tmp_path / "h.sqlite"
    shutil.copy(V1_FILE, db)
    con = sqlite3.connect(db)
    assert con.execute("SELECT version FROM schema_version").fetchall() == [(1,)]
    v1_rows = con.execute("SELECT id, record FROM runs ORDER BY id").fetchall()
    con.close()
    assert len(v1_rows) == 3
    with pytest.raises(SchemaError, match=r"schema 1: record one run .* --upgrade"):
        History(db, readonly=True)                  # reading never changes the file
    with History(db) as h:                          # a writer upgrades it
        runs_a = h.runs(UID_A)
        assert [r["note"] for r in runs_a] == ["v1 first", "v1 second"]
        assert [r["run_id"] for r in runs_a] == [1, 2]
        rep = H.device_report(h, UID_A)
        assert rep["drift"]["quantities"]["accel_bias_mg"]["axes"]["z"]["steps"][0]["change"] > 0
        new = h.record(production_result(UID_A, "2026-11-23T08:00:00+00:00"))
        assert new == 4
        assert h.run(new)["station_id"] == "S1" and h.run(1)["station_id"] is None
    con = sqlite3.connect(db)
    assert con.execute("SELECT version FROM schema_version").fetchall() == [(3,)]
    assert con.execute("SELECT id, record FROM runs WHERE id <= 3 ORDER BY id").fetchall() == v1_rows
    assert "parts" in {r[1] for r in con.execute("PRAGMA table_info(devices)")}     # schema 3
    cols = {r[1] for r in con.execute("PRAGMA table_info(runs)")}
    assert {"station_id", "operator", "fixture", "host_version", "params_before", "params_after",
            "capture_sha256", "capture_uri", "failure"} <= cols
    notnull = {r[1] for r in con.execute("PRAGMA table_info(runs)") if r[3]}
    assert "accel_m" not in notnull and "device_id" not in notnull
    con.close()
    assert imubench(["history", "--db", str(db), "--failed"]) == 0


def test_the_cli_upgrades_on_request(tmp_path, capsys):
    db = tmp_path / "h.sqlite"
    shutil.copy(V1_FILE, db)
    assert imubench(["history", "--db", str(db)]) == 1
    assert "--upgrade" in capsys.readouterr().err
    assert imubench(["history", "--db", str(db), "--upgrade"]) == 0
    assert "from schema 1 to 3" in capsys.readouterr().out
    assert imubench(["history", "--db", str(db), "--upgrade"]) == 0
    assert "already at schema 3" in capsys.readouterr().out
    assert imubench(["history", "--db", str(db)]) == 0
    assert UID_A in capsys.readouterr().out


def test_a_newer_database_is_refused_and_left_alone(target):
    with History(target) as h:
        h.record(production_result(UID_A, "2026-11-22T06:40:00+00:00"))
        with h._write() as db:
            db.execute(DB.schema_version.update().values(version=DB.SCHEMA_VERSION + 1))
    digest = hashlib.sha256(Path(target).read_bytes()).hexdigest() if "://" not in target else None
    for ro in (False, True):
        with pytest.raises(SchemaError, match="newer imubench .*nothing was changed"):
            History(target, readonly=ro)
    if digest:
        assert hashlib.sha256(Path(target).read_bytes()).hexdigest() == digest


def test_a_foreign_postgresql_database_is_not_taken_over(pg):
    url = pg.createdb("foreign_db")
    from sqlalchemy import create_engine
    eng = create_engine(url.replace("postgresql://", "postgresql+psycopg://"))
    with eng.begin() as c:
        c.exec_driver_sql("CREATE TABLE invoices (id int)")
    eng.dispose()
    with pytest.raises(SchemaError, match="not an imubench history.*invoices"):
        History(url)


def test_unreachable_server_is_one_clear_error(pg, capsys):
    url = f"postgresql://imubench@127.0.0.1:{pg.port + 1 if pg.port < 65535 else 1}/x"
    assert imubench(["history", "--db", url]) == 1
    err = capsys.readouterr().err
    assert err.startswith("imubench history: error: cannot open postgresql://imubench@127.0.0.1") and \
        len(err.strip().splitlines()) == 1


# ------------------------------------------------------------------ queries and export
def _line(target):
    """Two stations, two days, a session of four boards with one failure."""
    with History(target) as h:
        for k, (st, day, ok) in enumerate([("S1", 20, True), ("S1", 20, True), ("S1", 21, False), ("S2", 20, True),
                                           ("S2", 21, True), ("S2", 21, False), ("S2", 21, True)]):
            h.record(production_result(f"AAAA{k:020X}", f"2026-11-{day}T09:{k:02d}:00+00:00", station=st,
                                       passed=ok, k=k) | {"session_id": f"{st}-{day}"})


def test_yield_per_station_and_day(target, capsys):
    _line(target)
    with History(target, readonly=True) as h:
        rows = {(r["station"], r["day"]): (r["runs"], r["passed"]) for r in h.yield_table("station_day")}
        by_station = {r["station"]: r["yield"] for r in h.yield_table("station")}
        assert rows == {("S1", "2026-11-20"): (2, 2), ("S1", "2026-11-21"): (1, 0),
                        ("S2", "2026-11-20"): (1, 1), ("S2", "2026-11-21"): (3, 2)}
        assert by_station["S1"] == pytest.approx(2 / 3) and by_station["S2"] == pytest.approx(3 / 4)
        assert [r["runs"] for r in h.yield_table("day", station="S2")] == [1, 3]
        assert [r["day"] for r in h.yield_table("day", since="2026-11-21")] == ["2026-11-21"]
    assert imubench(["history", "--db", target, "--yield"]) == 0
    out = capsys.readouterr().out
    line = next(ln for ln in out.splitlines() if ln.startswith("S2") and "2026-11-21" in ln)
    assert line.split()[2:6] == ["3", "2", "1", "66.7"] and "%" in line
    assert "total" in out and "71.4 %" in out                   # 5 of 7
    assert imubench(["history", "--db", target, "--yield", "--json"]) == 0
    assert len(json.loads(capsys.readouterr().out)["yield"]) == 4


def test_failed_boards_and_why(target, capsys):
    _line(target)
    assert imubench(["history", "--db", target, "--failed"]) == 0
    out = capsys.readouterr().out
    assert out.count("accel_norm_rms_mg = 3.00 mg (limit ≤ 1 mg): FAIL") == 2
    assert "AAAA00000000000000000005" in out and "AAAA00000000000000000002" in out
    assert "2 failed runs" in out
    assert imubench(["history", "--db", target, "--failed", "--station", "S1"]) == 0
    assert "1 failed run" in capsys.readouterr().out


def test_export_json_and_junit(target, tmp_path, capsys):
    _line(target)
    with History(target, readonly=True) as h:
        runs = h.session_runs("S2-21")
    assert len(runs) == 3
    d = session_dict(runs)
    assert d["summary"] == {"boards": 3, "passed": 2, "failed": 1} and d["station_id"] == "S2"
    out = tmp_path / "s.xml"
    assert imubench(["history", "--db", target, "--export", "S2-21", "--format", "junit", "--out", str(out)]) == 0
    root = ET.parse(out).getroot()
    assert root.tag == "testsuites"
    suites = root.findall("testsuite")
    assert len(suites) == 3
    n_meas = len(measurements_of(production_result(UID_A, "2026-11-20T08:00:00+00:00")))
    assert int(root.get("tests")) == 3 * n_meas and int(root.get("failures")) == 2   # fit and write-back
    for s in suites:
        cases = s.findall("testcase")
        assert int(s.get("tests")) == len(cases) == n_meas
        props = {p.get("name"): p.get("value") for p in s.find("properties")}
        assert props["station_id"] == "S2" and props["operator"] == "ana" and len(props["capture_sha256"]) == 64
        fit = next(c for c in cases if c.get("name") == "accel_norm_rms_mg")
        fp = {p.get("name"): p.get("value") for p in fit.find("properties")}
        assert fp["unit"] == "mg" and float(fp["high"]) == 1.0
        failed = props["verdict"] == "failed"
        assert (fit.find("failure") is not None) == failed
        if failed:
            assert float(fp["value"]) == 3.0 and "FAIL" in fit.find("failure").get("message")
    assert "written to" in capsys.readouterr().out
    assert imubench(["history", "--db", target, "--export", "S2-21", "--format", "json"]) == 0
    js = json.loads(capsys.readouterr().out)
    assert [b["verdict"] for b in js["boards"]] == [b["verdict"] for b in d["boards"]]
    assert js["boards"][0]["measurements"][0]["name"] == "accel_norm_rms_mg"


def test_junit_of_a_board_that_never_answered():
    run = {"run_id": 9, "slot": 2, "port": "socket://x:2", "mcu_uid": None, "passed": False, "failure": "link lost",
           "failed_stage": "capture", "measurements": [], "started_utc": "2026-11-22T07:00:00.000000+00:00",
           "finished_utc": "2026-11-22T07:00:20.000000+00:00", "session_id": "s", "station_id": "S1"}
    root = ET.fromstring(junit_xml([run]))
    (suite,) = root.findall("testsuite")
    (case,) = suite.findall("testcase")
    err = case.find("error")
    assert err is not None and err.get("type") == "capture" and err.get("message") == "capture: link lost"
    assert suite.get("errors") == "1" and suite.get("time") == "20.0" and "slot 2 port socket://x:2" in suite.get("name")


def test_device_records_show_station_and_failure(target, capsys):
    with History(target) as h:
        h.record(production_result(UID_A, "2026-11-20T08:00:00+00:00", station="S1", slot=2))
        h.record(production_result(UID_A, "2026-11-21T08:00:00+00:00", station="S2", slot=1, passed=False))
    assert imubench(["history", "--db", target, UID_A[:6]]) == 0
    out = capsys.readouterr().out
    assert "station S1 slot 2, operator ana, fixture plate-4, host 0.1.0" in out
    assert "station S2 slot 1" in out
    assert "capture sha256 " + "0" * 64 in out
    assert "accel_norm_rms_mg = 3.00 mg (limit ≤ 1 mg): FAIL" in out


def test_env_names_the_database(target, monkeypatch, capsys):
    with History(target) as h:
        h.record(production_result(UID_A, "2026-11-20T08:00:00+00:00"))
    monkeypatch.setenv("IMUBENCH_DB", target)
    assert imubench(["history"]) == 0
    assert UID_A in capsys.readouterr().out


def _open_at_once(target: str, n: int = 4) -> None:
    from dbwriters import opener
    ctx = mp.get_context("spawn")
    barrier = ctx.Barrier(n)
    procs = [ctx.Process(target=opener, args=(target, barrier, w)) for w in range(n)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(120)
    assert [p.exitcode for p in procs] == [0] * n


def test_stations_opening_an_empty_database_at_once(target):
    """Four stations start at the same moment on a database nobody has created: the tables
    are created once, and every station's record arrives."""
    _open_at_once(target)
    with History(target, readonly=True) as h:
        assert h.count_runs() == 4
        with h._read() as db:
            assert db.execute(DB.schema_version.select()).all() == [(DB.SCHEMA_VERSION,)]


def test_stations_opening_a_schema_1_file_at_once(tmp_path):
    """... and on a file of the previous imubench (schema 1 existed only as SQLite files): it
    is upgraded once, the old runs kept."""
    db = tmp_path / "h.sqlite"
    shutil.copy(V1_FILE, db)
    _open_at_once(str(db))
    with History(db, readonly=True) as h:
        assert h.count_runs() == 3 + 4
        assert [r["note"] for r in h.runs(UID_A)] == ["v1 first", "v1 second"]
        with h._read() as d:
            assert d.execute(DB.schema_version.select()).all() == [(DB.SCHEMA_VERSION,)]


def test_a_session_id_with_underscores_and_percent_is_matched_literally(target):
    with History(target) as h:
        h.record(production_result(UID_A, "2026-11-20T08:00:00+00:00") | {"session_id": "line_1%-a"})
        h.record(production_result(UID_B, "2026-11-20T08:00:00+00:00") | {"session_id": "lineX1Z-b"})
        assert [r["mcu_uid"] for r in h.session_runs("line_1%")] == [UID_A]
        with pytest.raises(H.UnknownDevice, match="no session"):
            h.session_runs("line_1_")
