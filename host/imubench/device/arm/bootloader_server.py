"""The process while an emulated board is in its ROM bootloader: the serial endpoint and the
control channel of the simulation library served around the protocol engine (bootloader.py)."""
from __future__ import annotations


class BootloaderServer:
    """The process while the board is in its ROM bootloader: bytes from the serial endpoint
    (pty or TCP) to the protocol engine and back, the control channel served (power_cut,
    quit, status). Device time follows the wall clock (x speed) plus the flash busy time."""

    def __init__(self, rom, lib, speed: float, t0: float, log):
        """rom: the protocol engine (bootloader.RomBootloader, which names this class again)."""
        self.rom = rom
        self.lib = lib
        self.speed = speed if speed > 0 else 1.0
        self.t0 = t0
        self.log = log
        import time
        self._time = time
        self.wall0 = time.monotonic()
        self.busy0 = rom.busy_s
        self.power_cuts = 0

    def now(self) -> float:
        return self.t0 + (self._time.monotonic() - self.wall0) * self.speed + (self.rom.busy_s - self.busy0)

    def serve(self, should_stop) -> tuple:
        """Until the bootloader leaves (("go", addr) / ("reset",)) or the process stops (("stop",))."""
        import ctypes

        from . import simlib
        lib, rom = self.lib, self.rom
        pfd = (simlib.PollFd * 16)()
        buf = (ctypes.c_uint8 * 512)()
        lib.simlib_set_state(0, 0, 0, 0, 0, self.power_cuts, 0)
        while not should_stop():
            lib.simlib_set_time(round(self.now() * 1e6))
            lib.sim_control_check_waits()
            if lib.simlib_quit():
                return ("stop",)
            if lib.simlib_take_reset() == 2:
                rom.action = ("power_cut",)
            n = lib.simlib_link_rx_pending()
            while n:
                got = lib.simlib_link_pull(buf, min(n, len(buf)))
                if not got:
                    break
                rom.feed(bytes(buf[:got]))
                n = lib.simlib_link_rx_pending()
            out = rom.take_output()
            if out and rom.action != ("power_cut",):
                lib.simlib_set_time(round(self.now() * 1e6))
                lib.simlib_link_push(out, len(out))
                lib.simlib_link_flush()
            if rom.action is not None:
                act, rom.action = rom.action, None
                if act[0] == "power_cut":
                    self.power_cuts += 1
                    lib.simlib_set_state(0, 0, 0, 0, 0, self.power_cuts, 0)
                    self.log("power cut: the board restarts in its bootloader (BOOT0 high)")
                    lib.simlib_power_cycle_models()
                    lib.simlib_link_reset()
                    rom.reset()
                    continue
                return act
            # wait for bytes or a control request
            poller, lfd, cfd, slot, n_ctl = simlib.sim_poller(lib, pfd)
            try:
                ready = poller.poll(20)
            except InterruptedError:
                continue
            ctl = False
            for fd, ev in ready:
                if fd == lfd:
                    lib.simlib_link_accept()
                elif fd == cfd:
                    lib.simlib_link_receive()
                elif fd in slot:
                    pfd[slot[fd]].revents = ev
                    ctl = True
            if ctl:
                lib.sim_control_handle(pfd, n_ctl)
        return ("stop",)
