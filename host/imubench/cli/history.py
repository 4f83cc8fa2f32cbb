"""`imubench history [DEVICE]`: the devices a history database knows, or one device's runs and drift."""
from __future__ import annotations

import argparse
import json
from pathlib import Path


def _db_path(s: str) -> Path:
    p = Path(s)
    if p.is_dir():
        raise argparse.ArgumentTypeError(f"{s} is a directory: give the database file (e.g. {p / 'history.sqlite'})")
    return p


def register(sub) -> None:
    from imubench.results.history import default_path
    p = sub.add_parser("history", help="calibration history of a device",
                       description="Calibration history: the known devices, or one device's runs and how its "
                                   "bias and scale drifted between calibrations. Identifiers are hex, as "
                                   "`imubench info` prints them.")
    p.add_argument("device", nargs="?", metavar="DEVICE",
                   help="MCU UID, a unique prefix of it (at least 4 hex digits) or a gyro serial number (hex)")
    p.add_argument("--db", type=_db_path, metavar="PATH", help=f"history database (default: {default_path()})")
    p.add_argument("--json", action="store_true", help="print the same data as JSON")
    p.set_defaults(run=run)


def run(a) -> int:
    from imubench.results.history import (
        History,
        default_path,
        device_report,
        format_device_report,
        format_devices,
        strict_json,
    )
    path = a.db or default_path()
    if not path.exists() and a.db is None and a.device is None:
        # the default database does not exist until the first session records into it
        print(json.dumps({"database": str(path), "devices": []}) if a.json
              else f"no calibrations recorded yet ({path} does not exist)")
        return 0
    with History(path, readonly=True) as h:
        if a.device is None:
            devs = h.devices()
            if a.json:
                print(json.dumps(strict_json({"database": str(path), "devices": devs}), indent=1))
            else:
                print(format_devices(devs, path))
            return 0
        rep = device_report(h, a.device)
    if a.json:
        print(json.dumps(strict_json({"database": str(path), **rep}), indent=1, allow_nan=False))
    else:
        print(format_device_report(rep))
    return 0
