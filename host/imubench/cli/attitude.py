"""`imubench attitude`: live roll and pitch from the device's calibrated output, three filters."""
from __future__ import annotations

import csv
import sys
import time
from contextlib import nullcontext

import numpy as np

from imubench.cli.common import add_port, new_file, positive_float, stream_rate


def register(sub) -> None:
    p = sub.add_parser("attitude", help="live pitch/roll through RC, Kalman and complementary filters",
                       description="Live roll/pitch (deg) from the device's calibrated output; "
                                   "roll = atan2(fy, fz), pitch = atan2(-fx, hypot(fy, fz)), positive pitch = "
                                   "nose down (docs/attitude.md). Ctrl-C stops.")
    add_port(p)
    p.add_argument("--rate", type=stream_rate, metavar="HZ", default=200, help="sample rate in Hz")
    p.add_argument("--duration", type=positive_float, default=None, help="seconds to run (default: until Ctrl-C)")
    p.add_argument("--filter", choices=("rc", "kalman", "complementary", "all"), default="all",
                   help="which tilt filter(s) to run")
    p.add_argument("--num", type=positive_float, default=20, help="RC low-pass constant num in y += (x - y)/num")
    p.add_argument("--tau", type=positive_float, default=0.5, help="complementary filter time constant, s")
    p.add_argument("--record", type=new_file, metavar="FILE",
                   help="append the received bytes to FILE and write the angles to FILE.angles.csv (or --csv)")
    p.add_argument("--csv", type=new_file, metavar="FILE", help="write the angles to this CSV")
    p.add_argument("--print-hz", type=positive_float, default=4.0, help="live lines per second")
    p.set_defaults(run=run)


def run(a) -> int:
    from imubench.analysis.tilt import accel_tilt, make_filters
    from imubench.device.link import Device
    from imubench.procedures.attitude import live
    from imubench.wire.params import is_factory
    from imubench.wire.protocol_gen import ParamsWhich

    filters = make_filters(a.filter, a.num, a.tau)
    csv_path = a.csv or (f"{a.record}.angles.csv" if a.record else None)
    n_total = 0
    with open(a.record, "ab", buffering=0) if a.record else nullcontext() as capture, \
            open(csv_path, "w", newline="") if csv_path else nullcontext() as csv_file:
        writer = None
        if csv_path:
            writer = csv.writer(csv_file)
            writer.writerow(["t_s", "accel_roll_deg", "accel_pitch_deg"]
                            + [f"{f.name}_{c}_deg" for f in filters for c in ("roll", "pitch")])
        with Device.open(a.port, baudrate=a.baud, capture=capture if a.record else None) as dev:
            if is_factory(dev.get_params(ParamsWhich.ACTIVE).params):
                print("warning: this device has factory parameters: its \"calibrated\" output is the raw data "
                      "at nominal scale (calibrate it first: imubench calibrate)", file=sys.stderr, flush=True)
            print("   t (s)  " + "  ".join(f"{f.name:>10} roll/pitch (deg)" for f in filters), flush=True)
            next_print = time.monotonic()
            t_s = 0.0
            try:
                for block, t, res in live(dev, filters, a.rate, a.duration):
                    n_total += len(block)
                    t_s = float(t[-1])
                    if writer is not None:
                        ar, ap_ = accel_tilt(block.accel_mps2.astype(np.float64))
                        writer.writerows(np.column_stack([t, ar, ap_] + [c for r in res for c in r]).round(6).tolist())
                    now = time.monotonic()
                    if now >= next_print:
                        next_print = now + 1.0 / a.print_hz
                        print(f"{t_s:8.2f}  " + "  ".join(f"{f.name:>10} {r[0][-1]:+8.3f} {r[1][-1]:+8.3f}"
                                                         for f, r in zip(filters, res)), flush=True)
            except KeyboardInterrupt:
                pass                          # Ctrl-C is how a live view ends
    print(f"{n_total} samples over {t_s:.1f} s" + (f"; angles in {csv_path}" if csv_path else ""), file=sys.stderr)
    return 0

