"""`make demo`: a short session against a device, end to end through a real serial port.

Until the virtual device (the firmware core built for Linux, issue 3) exists, the demo
runs against the Python fake device (imubench.fakedev) on a pseudo-terminal and says so.
It checks the link, reads the device's identity, runs the self-test, streams raw samples
and reports their noise against the datasheet densities, writes calibration parameters,
reads them back bit-exactly, saves them, reboots, verifies they persisted, streams the
device's calibrated output, and decodes the capture it recorded on the way.
"""
from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

from . import params as PR
from . import units as U
from .cli import _print_info
from .decoder import decode_bytes
from .fakedev import ACCEL_NOISE_G_RTHZ, GYRO_NOISE_DPS_RTHZ, FakeDevice
from .link import Device
from .protocol_gen import ParamsWhich, ParamSource


def main() -> int:
    rate = 1000
    print("imubench demo: device = Python fake device on a pseudo-terminal (synthetic still board).")
    print("               The virtual device built from the firmware core replaces it with issue 3.\n")
    workdir = Path(tempfile.mkdtemp(prefix="imubench-demo-"))
    capture_path = workdir / "capture.bin"
    with FakeDevice(seed=7) as fake, open(capture_path, "wb") as cap, \
            Device.open(fake.port_url, capture=cap) as dev:
        print(f"port {fake.port_url}: ping {dev.ping() * 1e3:.2f} ms")
        _print_info(dev.info())
        st = dev.self_test()
        print(f"self-test: passed mask {st.passed:04b} of tested {st.tested:04b}")

        dev.start_stream(rate)
        raw = dev.read(n_samples=3 * rate)
        dev.stop_stream()
        acc = U.accel_counts_to_mps2(raw.accel_counts, raw.accel_range_g)
        gyr = U.gyro_counts_to_rad_s(raw.gyro_counts)
        print(f"\nraw stream: {len(raw)} samples at {rate} Hz, "
              f"|a| = {np.linalg.norm(acc.mean(axis=0)) / U.G0_MPS2:.5f} g")
        exp_a = ACCEL_NOISE_G_RTHZ * np.sqrt(rate) * 1e3
        exp_w = GYRO_NOISE_DPS_RTHZ * np.sqrt(rate)
        print(f"  accel noise [mg]   {U.mps2_to_mg(acc.std(axis=0)).round(3)}  (datasheet density -> {exp_a:.3f})")
        print(f"  gyro noise  [°/s]  {U.rad_s_to_dps(gyr.std(axis=0)).round(3)}  (datasheet density -> {exp_w:.3f})")

        p = PR.identity()
        p.accel_m = (1.002, 0.001, 0.0, 0.0, 0.998, 0.0, 0.0, 0.0, 1.001)
        p.accel_b_mps2 = (0.012, -0.020, 0.035)
        p.gyro_b_rad_s = (0.0012, -0.0004, 0.0009)
        PR.validate(p)
        dev.set_params(p)
        back = dev.get_params(ParamsWhich.ACTIVE).params
        same = back.STRUCT.pack(*back.values()) == p.STRUCT.pack(*p.values())
        print(f"\nparameters written; read back bit-exact: {same}")
        gen = dev.save_params()
        info = dev.reboot(wait_s=3.0)
        stored = dev.get_params(ParamsWhich.STORED)
        persisted = stored.params.STRUCT.pack(*stored.params.values()) == p.STRUCT.pack(*p.values())
        print(f"saved as generation {gen}; after reboot source {ParamSource(info.param_source).name}, "
              f"stored block identical: {persisted}")

        dev.start_stream(rate, calibrated=True)
        cal = dev.read(n_samples=rate)
        dev.stop_stream()
        print(f"calibrated stream: {len(cal)} samples, mean accel [m/s²] {cal.accel_mps2.mean(axis=0).round(4)}")
        link = dev.link.decoder.stats
        ok = same and link.frames_rejected == 0 and link.samples_missing == 0
    msgs, raw2, cal2, stats = decode_bytes(capture_path.read_bytes())
    print(f"\ncapture {capture_path}: {stats.bytes_in} bytes, {stats.frames_ok} frames, "
          f"{stats.frames_rejected} rejected; {len(raw2)} raw + {len(cal2)} calibrated samples")
    print(f"\ndemo {'PASSED' if ok else 'FAILED'}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
