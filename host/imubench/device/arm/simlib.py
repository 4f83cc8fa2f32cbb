"""ctypes binding of libimumodels.so (firmware/boards/sim/sim_lib.c): the virtual
device's sensor models, physics, control channel and serial endpoint, shared with the ARM
emulator so both targets run against ONE set of models.

The library keeps its state in C globals (one world per process): the emulator runs in its
own process (`python -m imubench.device.arm`), one device per process, like imubench-sim.
imubench.device.artifacts.models_library() finds the file (the installed package's, or the
checkout's build/host/).
"""
from __future__ import annotations

import ctypes
from ctypes import (
    POINTER,
    c_char_p,
    c_double,
    c_int,
    c_size_t,
    c_uint8,
    c_uint16,
    c_uint32,
    c_uint64,
    c_void_p,
)
from pathlib import Path

from imubench.errors import ImubenchError

class SimLibError(ImubenchError, RuntimeError):
    """The models library is missing or could not be loaded."""


class PollFd(ctypes.Structure):
    _fields_ = [("fd", c_int), ("events", ctypes.c_short), ("revents", ctypes.c_short)]


_SIGNATURES = {
    "simlib_open": (c_int, [c_uint64, c_int, c_char_p, c_int, c_int, c_double]),
    "simlib_set_parts": (c_int, [c_char_p, c_char_p, c_int]),
    "simlib_close": (None, []),
    "simlib_set_pty": (None, [c_int]),
    "simlib_set_identity_target": (None, [c_char_p]),
    "simlib_pty_name": (c_char_p, []),
    "simlib_set_log": (None, [c_int]),
    "simlib_tcp_port": (c_int, []),
    "simlib_control_port": (c_int, []),
    "simlib_uid": (None, [POINTER(c_uint8)]),
    "simlib_speed": (c_double, []),
    "simlib_quit": (c_int, []),
    "simlib_set_time": (None, [c_uint64]),
    "simlib_time": (c_uint64, []),
    "simlib_set_state": (None, [c_int, c_uint32, c_uint64, c_uint64, c_uint32, c_uint32, c_uint32]),
    "simlib_set_target": (None, [c_char_p, c_uint64, c_uint64, c_uint64, c_uint64, c_double, c_double]),
    "simlib_take_reset": (c_int, []),
    "simlib_set_arm_detail": (None, [POINTER(c_uint64), c_uint64, c_double, c_double, c_double, c_uint64, c_uint64,
                                     c_double]),
    "simlib_spi_peek": (c_int, [c_int, c_char_p, POINTER(c_uint8), c_size_t]),
    "simlib_spi_commit": (c_int, [c_int, c_char_p, POINTER(c_uint8), c_size_t]),
    "simlib_power_cycle_models": (None, []),
    "simlib_flash_op": (c_int, []),
    "simlib_flash_boot": (None, []),
    "simlib_link_fds": (None, [POINTER(c_int), POINTER(c_int)]),
    "simlib_link_accept": (c_int, []),
    "simlib_link_receive": (None, []),
    "simlib_link_flush": (None, []),
    "simlib_link_staged": (c_size_t, []),
    "simlib_link_blocked": (c_int, []),
    "simlib_link_push": (c_size_t, [c_char_p, c_size_t]),
    "simlib_link_rx_pending": (c_size_t, []),
    "simlib_link_pull": (c_size_t, [POINTER(c_uint8), c_size_t]),
    "simlib_link_reset": (None, []),
    "simlib_counter_setup": (None, [c_void_p, POINTER(c_uint16), c_uint32, c_uint32, POINTER(c_uint8)]),
    "simlib_icount": (c_uint64, []),
    "simlib_set_limit": (None, [c_uint64]),
    "simlib_region_counts": (None, [POINTER(c_uint64)]),
    "sim_control_pollfds": (c_int, [POINTER(PollFd), c_int]),
    "sim_control_handle": (None, [POINTER(PollFd), c_int]),
    "sim_control_check_waits": (None, []),
    "sim_control_next_deadline": (c_uint64, []),
    "simlib_next_event": (c_uint64, []),
    "simlib_set_lockstep": (None, [c_int]),
    "sim_control_run_target": (c_int, [POINTER(c_uint64)]),
}


def load(path: Path) -> ctypes.CDLL:
    """Load the library and declare every entry point's signature."""
    if not path.is_file():
        raise SimLibError(f"{path} is missing: build it with `make sim`")
    try:
        lib = ctypes.CDLL(str(path))
    except OSError as e:
        raise SimLibError(f"cannot load {path}: {e}") from e
    for name, (res, args) in _SIGNATURES.items():
        fn = getattr(lib, name)
        fn.restype = res
        fn.argtypes = args
    return lib


def sim_poller(lib: ctypes.CDLL, pfd, cfd_events: int | None = None):
    """One poll set over what the models library serves: the link's listening socket, its
    connected client (cfd_events, default POLLIN) and the control channel's descriptors
    (filled into pfd). Returns (poller, lfd, cfd, slot, n_ctl): slot maps a control fd to its
    index in pfd, whose revents the caller sets before sim_control_handle(pfd, n_ctl)."""
    import select
    lfd, cfd = ctypes.c_int(), ctypes.c_int()
    lib.simlib_link_fds(ctypes.byref(lfd), ctypes.byref(cfd))
    poller = select.poll()
    if lfd.value >= 0:
        poller.register(lfd.value, select.POLLIN)
    if cfd.value >= 0:
        poller.register(cfd.value, select.POLLIN if cfd_events is None else cfd_events)
    n_ctl = lib.sim_control_pollfds(pfd, 16)
    slot = {}
    for i in range(n_ctl):
        slot[pfd[i].fd] = i
        pfd[i].revents = 0
        poller.register(pfd[i].fd, pfd[i].events)
    return poller, lfd.value, cfd.value, slot, n_ctl
