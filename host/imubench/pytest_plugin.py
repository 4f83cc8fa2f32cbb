"""pytest fixtures for testing against an imubench device (registered as a pytest plugin).

    def test_my_board(imubench_device):
        assert imubench_device.info().sensors_present == 0b1111

`imubench_device` is an open, pinged imubench.device.link.Device. It connects to the port given by
`--imubench-port URL` or the environment variable IMUBENCH_PORT (a real board: /dev/ttyUSB0,
socket://..., rfc2217://...); with neither, it starts the virtual device for the session,
so a bench and CI differ only in that URL. `virtual_bench` gives the VirtualBench itself
(for tests that drive the control channel); it always starts the virtual device.
"""
from __future__ import annotations

import os

import pytest


def pytest_addoption(parser):
    g = parser.getgroup("imubench")
    g.addoption("--imubench-port", default=None,
                help="pyserial URL of the device under test (default: $IMUBENCH_PORT, else the virtual device)")
    g.addoption("--imubench-sim-speed", type=float, default=None,
                help="speed factor of the virtual device when one is started: on the lockstep clock a "
                     "ceiling (default none), on the real-time clock the pace (default 20)")
    g.addoption("--imubench-sim-clock", choices=("lockstep", "realtime"), default=None,
                help="clock of the virtual device: lockstep (the default; deterministic, nothing dropped) or "
                     "realtime (against the wall clock, as a real board)")


@pytest.fixture(scope="session")
def virtual_bench(request):
    from imubench.device.sim import VirtualBench
    with VirtualBench(speed=request.config.getoption("--imubench-sim-speed"),
                      clock=request.config.getoption("--imubench-sim-clock")) as vb:
        yield vb


@pytest.fixture(scope="session")
def imubench_port(request) -> str:
    url = request.config.getoption("--imubench-port") or os.environ.get("IMUBENCH_PORT")
    if url:
        return url
    return request.getfixturevalue("virtual_bench").port_url


@pytest.fixture
def imubench_device(imubench_port):
    from imubench.device.link import Device
    with Device.open(imubench_port, timeout=3.0) as dev:
        dev.ping()
        yield dev
