"""`imubench calibrate` once a fit is known: what is printed (the tables, the virtual device's
truth), what the record carries for a station (its fields, the parameters before and after),
the closure check after a write-back, and the history (opened before anything is captured,
recorded after). Shared by a device's session (cli.calibrate) and a recording's (cli.calibrate_file)."""
from __future__ import annotations

import sys
from pathlib import Path

from imubench.cli.common import CommandError


def _check_history(db) -> None:
    """Open the history database before anything is captured: a database that is down or a
    path that cannot be written is named now, not after a session whose record it would lose."""
    from imubench.results.db import describe
    from imubench.results.history import History, default_target
    import os
    target = db or default_target()
    path = None if "://" in str(target) else Path(target)
    if path is not None and not path.exists():
        # a new SQLite file: made by the first record, not now (a command refused later, e.g. a
        # usage error, leaves no empty database behind); here only whether it can be made
        parent = path.parent if str(path.parent) else Path(".")
        probe = next((q for q in [parent, *parent.parents] if q.exists()), None)
        if probe is None or not probe.is_dir() or not os.access(probe, os.W_OK | os.X_OK):
            raise CommandError(f"history database: {describe(target)}: cannot create it ({probe or parent} "
                               "is not a writable directory)",
                               "fix --db (or IMUBENCH_DB); nothing was captured")
        return
    try:
        with History(target, timeout_s=5.0):
            pass
    except Exception as e:  # noqa: BLE001 - any failure to open is the same answer to the user
        text = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        if describe(target) not in text:
            text = f"{describe(target)}: {text}"
        raise CommandError(f"history database: {text}",
                           "start the database or fix --db (or IMUBENCH_DB); nothing was captured") from None


def _print_fit(vb):
    """What the session prints once the fit is known (and, on a virtual device, the truth)."""
    def report(result: dict) -> None:
        from imubench.results.calibration import (
            before_after_table,
            params_table,
            truth_table,
        )
        print()
        print(params_table(result))
        print()
        print(before_after_table(result))
        if vb is not None:
            print("\nrecovered beside the virtual device's truth:")
            print(truth_table(result, vb.get_truth()))
    return report


def _closure_after_session(dev, vb, out: Path) -> dict:
    """The closure check with the parameters just written (imubench.procedures.closure): a
    summary for the session's result; the details are in out."""
    from imubench.analysis.strapdown import ClosureError
    from imubench.procedures.closure import run_closure
    from imubench.results.closure import summarize
    from imubench.wire.protocol_gen import ParamsWhich
    print("\nclosure check: integrating a closed path before and after calibration")
    try:
        res = run_closure(dev, out, dev.get_params(ParamsWhich.ACTIVE).params, vb, "box")
    except ClosureError as e:           # the calibration stands; say why there is no figure
        print(f"closure check not possible: {e}", file=sys.stderr)
        return {"error": str(e)}
    print(summarize(res))
    print(f"closure details: {out / 'closure.json'}, plot {out / 'closure.png'}")
    return {"dir": str(out), "before_m": res["before"].distance_m, "after_m": res["after"].distance_m,
            "after_rest_bias_m": res["after_rest_bias"].distance_m,
            "noise_floor_m": res["noise_floor"]["sigma_distance_m"]}


def _record_history(result: dict, db, state_path: Path) -> None:
    from imubench.results.history import History
    try:
        with History(db) as h:
            run_id, new = h.record_once(result)
        print(f"recorded in the history as run {run_id}" if new else
              f"already recorded in the history as run {run_id} (the same run: not recorded twice)")
    except Exception as e:  # noqa: BLE001 - the result is safe in session.json; say why it is not in the history
        print(f"warning: not recorded in the history ({e}); the result is in {state_path}", file=sys.stderr)


def _params_or_none(dev):
    from imubench.wire.protocol_gen import ParamsWhich
    try:
        return dev.get_params(ParamsWhich.ACTIVE).params
    except Exception:  # noqa: BLE001 - the record says "unknown" rather than failing the session
        return None


def _add_station_fields(result: dict, a, directory: Path, before, after, url) -> None:
    """What a one-board session's record carries for the production database (schema 2):
    station, operator, fixture, host version, parameters before and after, raw capture hash."""
    from imubench.procedures.fixture import Station, capture_ref
    from imubench.wire import params as PR
    sf = getattr(a, "station_file", None) or {}
    st = Station(station_id=getattr(a, "station", None) or sf.get("station", ""),
                 operator=getattr(a, "operator", "") or sf.get("operator", ""),
                 fixture=getattr(a, "fixture", "") or sf.get("fixture", ""))
    result["station"] = {"id": st.station_id, "operator": st.operator, "fixture": st.fixture, "slot": 1,
                         "port": url, "host_version": st.host_version}
    result["params_before"] = PR.to_json(before) if before is not None else None
    result["params_after"] = PR.to_json(after) if after is not None and result.get("written") else None
    result["capture"] = capture_ref(directory)
