"""Serving an emulated board (machine.Machine): its serial endpoint and control channel on
sockets or a pty, paced to the requested speed against the wall clock (the real-time clock),
or in lockstep: frozen except inside a run the host grants (firmware/boards/sim/sim_control.c
"run"; the same semantics as imubench-sim's --clock lockstep, sim_main.c)."""
from __future__ import annotations

import ctypes
import select
import time

from . import simlib
from .machine import INF, MAX_LAG_WALL_S, RESET_POWER_CUT, Machine


class Server:
    """The process around a Machine: the serial endpoint and control channel of
    libimumodels.so, pacing device time against the wall clock (speed), as imubench-sim."""

    def __init__(self, machine: Machine, lib, speed: float, lockstep: bool = False):
        self.lockstep = lockstep
        self.m = machine
        self.lib = lib
        self.speed = speed
        lib.simlib_set_time(round(machine.now() * 1e6))
        self.anchor_wall = time.monotonic()
        self.anchor_dev = machine.now()
        self.slips = 0
        self.quit = False
        self._bp_since: float | None = None

    def _pace_target(self, wall: float) -> float:
        return self.anchor_dev + (wall - self.anchor_wall) * (self.speed if self.speed > 0 else 1.0)

    def serve(self, should_stop=lambda: False) -> None:
        if self.lockstep:
            return self._serve_lockstep(should_stop)
        lib, m = self.lib, self.m
        pfd = (simlib.PollFd * 16)()
        last_wall = time.monotonic()
        while not self.quit and not should_stop() and not m.exit_to_rom:
            wall = time.monotonic()
            sp = lib.simlib_speed()
            if sp != self.speed:  # control channel set_speed
                self.anchor_dev = m.now() if self.speed == 0 else self._pace_target(wall)
                self.anchor_wall = wall
                self.speed = sp
            now = m.now()
            m.set_model_time(now)
            ext = lib.simlib_next_event()
            # a deadline already reached is not one to stop at: the models catch up with it at
            # the next set_model_time (e.g. once an open SPI transaction is committed)
            m.ext_deadline = ext * 1e-6 if ext != 0xFFFFFFFFFFFFFFFF and ext * 1e-6 > now else INF
            m._recompute_next()
            if self.speed > 0:
                target = self._pace_target(wall)
                if target - now > MAX_LAG_WALL_S * self.speed:
                    self.anchor_dev, self.anchor_wall = now, wall
                    target = now
                    self.slips += 1
            else:
                # as fast as it goes; when the host does not read, wait up to 50 ms for it
                # (as imubench-sim does), then run on
                target = now + 0.05
                if lib.simlib_link_blocked() and lib.simlib_link_staged() > 32768:
                    if self._bp_since is None:
                        self._bp_since = wall
                    if wall - self._bp_since < 0.05:
                        target = now
                else:
                    self._bp_since = None
            idle_cap = INF
            if self.speed == 0:
                idle = now + (wall - last_wall)
                idle_cap = m.ext_deadline if m.ext_deadline != INF and m.ext_deadline > idle else idle
            last_wall = wall
            if target > now:
                m.run_until(target, 0.02, idle_cap)
            now = m.now()
            m.usart.drain(now)
            m.set_model_time(now)
            if lib.simlib_link_staged():
                lib.simlib_link_flush()
            m.publish()
            lib.sim_control_check_waits()
            if lib.simlib_quit():
                break
            # how long to wait for I/O
            if self.speed > 0:
                ahead = now - self._pace_target(time.monotonic())
                timeout = min(max(ahead / self.speed, 0.0), 0.02) if ahead > 0 else 0.0
                nxt = min(m.next_ev, m.ext_deadline)
                if ahead <= 0 and nxt > now:
                    timeout = min((nxt - now) / self.speed, 0.02) if nxt != INF else 0.02
            else:
                asleep = m.cpu.wfi and not m.streaming() and m.ext_deadline == INF
                timeout = 0.002 if asleep else 0.0
            self._io(pfd, timeout)
            k = lib.simlib_take_reset()
            if k == RESET_POWER_CUT:
                m.request_reset("power_cut", "power cut (control channel)")
                m.take_reset()
                if m.exit_to_rom:
                    break
            m.usart.schedule_rx(m.now())

    def _io(self, pfd, timeout: float) -> None:
        lib = self.lib
        out = select.POLLOUT if lib.simlib_link_blocked() and lib.simlib_link_staged() else 0
        poller, lfd, cfd, slot, n_ctl = simlib.sim_poller(lib, pfd, select.POLLIN | out)
        try:
            ready = poller.poll(max(timeout, 0.0) * 1000.0)
        except InterruptedError:
            return
        ctl_ready = False
        for fd, ev in ready:
            if fd == lfd:
                if lib.simlib_link_accept() == 0:
                    self.m.log("link: TCP client connected")
            elif fd == cfd:
                if ev & (select.POLLIN | select.POLLHUP | select.POLLERR):
                    lib.simlib_link_receive()
                if ev & select.POLLOUT:
                    lib.simlib_link_flush()
            elif fd in slot:
                pfd[slot[fd]].revents = ev
                ctl_ready = True
        if ctl_ready:
            spi = self.m.spi
            if spi.cs is not None and spi.tx:
                # a fault injected now changes the sensor's answer between the bytes the image
                # has received and the transaction committed at chip select rise
                spi.control_during_transaction = True
            lib.sim_control_handle(pfd, n_ctl)

    # ------------------------------------------------------------ lockstep
    def _serve_lockstep(self, should_stop) -> None:
        """Run only inside a granted run: take the host's link bytes, run the image to the
        run's end (segments end at events and at the end only, so the wall clock decides
        nothing), hand every byte to the host waiting for it to read, reply; speed > 0 is a
        ceiling (the reply waits until the wall clock allows the device time it ran)."""
        lib, m = self.lib, self.m
        pfd = (simlib.PollFd * 16)()
        target = ctypes.c_uint64()
        active = False
        # the control command "quit" (lib.simlib_quit) ends it between grants too: checked only
        # after a grant, an idle device ran on until the host's SIGTERM, 3 s after the quit
        while not self.quit and not should_stop() and not m.exit_to_rom and not lib.simlib_quit():
            st = lib.sim_control_run_target(ctypes.byref(target))
            if st == 2:
                while lib.simlib_link_accept() == 0:
                    m.log("link: TCP client connected")
                lib.simlib_link_receive()
                st = lib.sim_control_run_target(ctypes.byref(target))
            if st == 1:
                if not active:      # a new grant: the host's bytes start arriving now
                    self.anchor_wall, self.anchor_dev, active = time.monotonic(), m.now(), True
                    m.usart.schedule_rx(m.now())
                self.speed = lib.simlib_speed()
                until = target.value * 1e-6
                now = m.now()
                # the grant's end is the only stop (no wall budget): the models, the link and the
                # status are brought to device time there alone, and the float device time is
                # summed over the same segments whatever the machine's load (the models library
                # hands the link bytes to the host as they fill up, waiting for it)
                m.ext_deadline = INF
                m._recompute_next()
                if until > now:
                    m.run_until(until, INF)
                elif lib.simlib_time() < target.value:
                    # at the end, but an SPI transaction holds the models at its chip select:
                    # run on (by the image alone) until it closes
                    m.run_until(now + 1e-6, INF)
                now = m.now()
                final = now >= until
                if final:
                    m.usart.drain(now)
                    m.set_model_time(now)
                self._flush_blocking()
                if not final:
                    self._io(pfd, 0.0)
                    continue
                if self.speed > 0:                          # the ceiling
                    ahead = now - self._pace_target(time.monotonic())
                    if ahead > 0:
                        time.sleep(ahead / self.speed)
                m.publish()
                lib.sim_control_check_waits()
                if lib.simlib_quit():
                    break
                active = lib.sim_control_run_target(None) == 1
            else:
                active = False
            self._io(pfd, 0.0 if active else 0.02)
            k = lib.simlib_take_reset()
            if k == RESET_POWER_CUT:
                m.request_reset("power_cut", "power cut (control channel)")
                m.take_reset()
                if m.exit_to_rom:
                    break

    def _flush_blocking(self) -> None:
        """Every staged link byte to the host, waiting while its socket is full."""
        lib = self.lib
        while lib.simlib_link_staged():
            lib.simlib_link_flush()
            if lib.simlib_link_blocked():
                lfd, cfd = ctypes.c_int(), ctypes.c_int()
                lib.simlib_link_fds(ctypes.byref(lfd), ctypes.byref(cfd))
                if cfd.value < 0:
                    break
                p = select.poll()
                p.register(cfd.value, select.POLLOUT)
                p.poll(100)
