"""The record of each board of a station session (procedures.fixture): schema 2 with the
station, slot, port, the parameter block before and after, its measurements and the SHA-256 of
its raw capture; a board that failed gets one with the stage and reason. On disk first
(slot-K/record.json), then in the history database.
"""
from __future__ import annotations

import hashlib
import socket
from pathlib import Path

from imubench.files import open_input
from imubench.results.atomic import write_json_atomic
from imubench.results.record import CalibrationRecord, jsonable, verdict
from imubench.wire import params as PR


class FixtureRecords:
    """The records half of FixtureRun (its state: boards, station, session_id, dir, cfg, db,
    _update, say)."""

    def _record_for(self, slot: int, started: str, result: dict | None, ident: dict, params_before, link_stats) -> dict:
        st = self.boards[slot]
        base = {"session_id": self.session_id,
                "station": {"id": self.station.station_id, "operator": self.station.operator,
                            "fixture": self.station.fixture, "slot": slot, "port": st.port,
                            "host_version": self.station.host_version},
                "params_before": PR.to_json(params_before) if params_before is not None else None,
                "capture": capture_ref(self.dir / f"slot-{slot}")}
        if link_stats is not None:
            base["link"] = {"samples_missing": int(link_stats.samples_missing),
                            "frames_rejected": int(link_stats.frames_rejected),
                            "samples_overflow": int(getattr(link_stats, "samples_overflow", 0))}
        from imubench.results.export import measurements_of
        if result is not None and st.state not in ("failed", "stopped"):
            rec = {**result, **base}
            rec["measurements"] = measurements_of(rec)
            ok, why = verdict(rec, self.cfg.write)
            if not ok:
                rec["passed"] = False
                self._update(slot, state="failed", stage=st.stage, reason="; ".join(why) or "did not pass",
                             message="FAILED: " + ("; ".join(why) or "did not pass"))
            else:
                self._update(slot, state="passed", stage="done", progress=1.0, message="PASSED")
            return rec
        # failed before or during the run: what is known, the stage and the reason
        fitted = {k: result[k] for k in ("accel", "gyro", "poses", "tolerances", "accel_rms_after_mg",
                                         "temperature_c", "verification") if result is not None and k in result}
        rec = CalibrationRecord(
            device=ident, started=started, method=self.cfg.method, gyro_method=self.cfg.gyro, note=self.cfg.note,
            written=bool(result and result.get("written")), capture_dir=str((self.dir / f"slot-{slot}").resolve()),
            failure={"stage": st.stage, "reason": st.reason or "failed", "stopped": st.state == "stopped"},
            **fitted, sections={**base, "params_after": (result or {}).get("params_after")}).to_json()
        rec["measurements"] = measurements_of(rec)
        return rec

    def _record(self, slot: int, rec: dict) -> None:
        try:                            # on disk first: the database may be slow, shared or gone
            (self.dir / f"slot-{slot}").mkdir(parents=True, exist_ok=True)
            write_json_atomic(self.dir / f"slot-{slot}" / "record.json", jsonable(rec))
        except OSError as e:
            self.say(f"warning: slot {slot}: record.json not written ({e})")
        if self.db is None:
            return
        from imubench.results.history import History
        self._update(slot, message=self.boards[slot].message, publish=False)
        try:
            with History(self.db) as h:
                run_id, _ = h.record_once(rec)
            self._update(slot, run_id=run_id)
        except Exception as e:  # noqa: BLE001 - the record is safe on disk; say why it is not in the database
            self.say(f"warning: slot {slot} not recorded in the history ({e}); its record is in "
                     f"{self.dir / f'slot-{slot}' / 'record.json'}")
        finally:
            try:
                write_json_atomic(self.dir / f"slot-{slot}" / "record.json", jsonable(rec))
            except OSError:
                pass


def capture_ref(d: Path) -> dict:
    """SHA-256 of the raw capture (the capture files in stream order, as one byte sequence),
    the files, and where they are: a file:// URI naming this station's host."""
    files = sorted(d.glob("capture-*.bin"), key=lambda p: int(p.stem.split("-")[1]) if p.stem.split("-")[1].isdigit() else 0)
    h = hashlib.sha256()
    listed = []
    for p in files:
        fh = hashlib.sha256()
        with open_input(p) as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                h.update(chunk)
                fh.update(chunk)
        listed.append({"name": p.name, "bytes": p.stat().st_size, "sha256": fh.hexdigest()})
    host = socket.gethostname()
    return {"sha256": h.hexdigest() if files else None,
            "uri": f"file://{host}{(files[0] if len(files) == 1 else d).resolve()}" if files else None,
            "files": listed}
