"""Worker processes for the concurrent-writer tests (tests/results/test_production_db.py): importable
by a spawned child, which gets the parent's sys.path."""
from __future__ import annotations

import time


def production_result(uid: str, started: str, station: str = "S1", slot: int = 1, passed: bool = True,
                      writer: int = 0, k: int = 0) -> dict:
    """A schema-2 record as the fixture procedure writes it, with five measurements."""
    import numpy as np
    m = (np.eye(3) + np.diag([250e-6, -310e-6, 80e-6])).tolist()
    return {
        "schema": 2,
        "device": {"mcu_uid": uid, "board": "SIM", "fw_version": "0.2.0", "fw_build": "sim-0.1.0",
                   "accel_ids": [173, 29, 237, 1], "gyro_pid": [20993] * 3, "gyro_sn": [1001, 1002, 1003]},
        "started": started, "finished": started, "session_started": started,
        "method": "six", "gyro_method": "bias",
        "accel": {"m": m, "b_mps2": [0.01, -0.02, 0.03], "sigma_m": np.full((3, 3), 3e-6).tolist(),
                  "sigma_b_mps2": [2e-5] * 3, "residual_rms_mps2": 1e-4},
        "gyro": {"method": "bias", "m": np.eye(3).tolist(), "b_rad_s": [1e-3, -2e-3, 5e-4],
                 "sigma_m": [[0.0] * 3] * 3, "sigma_b_rad_s": [1e-5] * 3, "residual_rms": 0.0},
        "poses": [{"name": f"pose{i}", "n": 1000, "before_g": 1.01, "after_g": 1.0, "sigma_g": 2e-5, "temp_c": 25.0}
                  for i in range(6)],
        "tolerances": {"accel_rms_mg": 1.0, "verify_mg": 2.0},
        "accel_rms_after_mg": 0.01 if passed else 3.0,
        "passed": passed, "written": passed, "verified": passed,
        "verification": [{"name": n, "after_g": 1.0002} for n in ("+X up", "-X up", "+Y up")],
        "note": f"writer {writer} record {k}", "capture_dir": f"/data/{station}/{k}",
        "station": {"id": station, "operator": "ana", "fixture": "plate-4", "slot": slot, "port": f"socket://x:{slot}",
                    "host_version": "0.1.0"},
        "session_id": f"{station}-{writer}-{k // 4}",
        "params_before": {"cal_id": 0}, "params_after": {"cal_id": k} if passed else None,
        "capture": {"sha256": f"{k:064x}", "uri": f"file:///data/{station}/{k}/capture.bin"},
    }


def writer(target: str, writer_no: int, n: int, barrier, shared_uid: str) -> int:
    """Record n runs as fast as possible once every writer is ready; every third run is of a
    device all writers share (contention on one device row)."""
    from imubench.results.history import History
    barrier.wait(timeout=60)
    with History(target, timeout_s=60) as h:
        for k in range(n):
            uid = shared_uid if k % 3 == 0 else f"{writer_no:04X}{k:020X}"
            # microseconds keep starts unique across writers for the shared device
            started = f"2026-11-{20 + k % 5:02d}T{8 + writer_no:02d}:{k // 60:02d}:{k % 60:02d}.{writer_no:06d}+00:00"
            h.record(production_result(uid, started, station=f"S{writer_no}", slot=1 + k % 4,
                                       passed=k % 5 != 0, writer=writer_no, k=k))
    return n


def reader(target: str, stop_at: float, expected: int, out) -> None:
    """While the writers write: every run visible has all its measurements (never half a record)."""
    from imubench.results.history import History
    from sqlalchemy import text
    bad, seen, polls = [], 0, 0
    with History(target, readonly=True, timeout_s=60) as h:
        while time.monotonic() < stop_at or polls < 6:     # a loaded machine may start it late
            with h._read() as db:
                rows = db.execute(text("SELECT r.id, r.record, COUNT(m.id) FROM runs r LEFT JOIN measurements m "
                                       "ON m.run_id = r.id GROUP BY r.id, r.record")).all()
            polls += 1
            seen = max(seen, len(rows))
            for rid, rec, nm in rows:
                if nm != expected:
                    bad.append((rid, nm))
            time.sleep(0.01)
    out.put({"bad": bad[:10], "seen": seen, "polls": polls})


def opener(target: str, barrier, writer_no: int) -> None:
    """Open a database that may still be empty (or old) at the same moment as other stations,
    and record one run."""
    from imubench.results.history import History
    barrier.wait(timeout=60)
    with History(target, timeout_s=60) as h:
        h.record(production_result(f"{writer_no:024X}", "2026-11-20T08:00:00+00:00", station=f"S{writer_no}"))
