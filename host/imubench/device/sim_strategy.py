"""The virtual bench's strategy: bringing it into a state, in order.

    off ──start()──▶ running ──stop()──▶ off ──close()──▶ gone
                     running ──restart()──▶ running (same flash file, same ports if free)

`transition("running")` / `transition("off")` (labgrid's name) goes wherever the bench is
asked to be. Starting is: spawn the process (the resource), connect the control channel,
register the lockstep clock for the link URL and the pty (imubench.device.clock: a Device
opened on that URL, also in another process, grants device time through it), and switch the
dies' thermal model on when the bench was made with it. Stopping is: quit over the channel,
then end the process (SIGTERM, SIGKILL) and reap it. The resource and the drivers know
nothing of these steps.
"""
from __future__ import annotations

from imubench.device import clock as clocks
from imubench.device.sim_drivers import ClimateDriver, ControlChannel
from imubench.device.sim_resource import SimError, SimProcess

__all__ = ["STATES", "BenchStrategy"]

STATES = ("off", "running", "gone")


class BenchStrategy:
    """The states of one bench: its resource, its control channel, its clock and the climate
    driver (the thermal model switched on at every start when asked)."""

    def __init__(self, resource: SimProcess, channel: ControlChannel, clock, climate: ClimateDriver, owner):
        self.resource, self.channel, self.clock, self.climate = resource, channel, clock, climate
        self.owner = owner          # what LIVE holds while the process runs (stopped at interpreter exit)

    @property
    def state(self) -> str:
        if self.resource.removed:
            return "gone"
        return "running" if self.resource.running else "off"

    def transition(self, state: str) -> None:
        """Bring the bench to `state` ("running", "off" or "gone"); nothing when it is there."""
        if state not in STATES:
            raise ValueError(f"state must be one of {', '.join(STATES)}, not {state!r}")
        if state == self.state:
            return
        if state == "running":
            self.start()
        elif state == "off":
            self.stop()
        else:
            self.close()

    def start(self) -> None:
        r = self.resource
        if r.removed:
            raise SimError("the virtual bench was closed: make a new one")
        self._start(r.tcp_request, r.control_request)

    def _start(self, tcp_port: int | None, control_port: int) -> None:
        r = self.resource
        r.spawn(tcp_port, control_port, self.owner)
        try:
            self.channel.connect()
            if self.clock.lockstep:
                self.clock.sync()
                clocks.unregister(self.clock)
                clocks.register(r.port_url, self.clock, control=r.info["control"])
                if r.pty:
                    clocks.register(r.pty, self.clock, control=r.info["control"])
            if r.thermal:
                self.climate.set_thermal(True)
        except BaseException:
            self.kill()
            raise

    def stop(self, timeout: float = 3.0) -> None:
        """Quit, then SIGTERM, then SIGKILL the process group; always reaps it. The flash file
        is kept."""
        if self.resource.proc is None:
            return
        self.channel.quit()
        self.resource.end(timeout)

    def kill(self) -> None:
        self.resource.kill()
        self.channel.disconnect()

    def restart(self) -> None:
        """Stop and start again with the same flash file (saved parameters survive) and, if
        they are still free, the same ports."""
        r = self.resource
        old_tcp, old_ctl = r.info.get("tcp_port"), r.info.get("control_port")
        self.stop()
        tcp = None if r.tcp_request is None else (old_tcp if old_tcp is not None else r.tcp_request)
        try:
            self._start(tcp, old_ctl if old_ctl is not None else r.control_request)
        except SimError:
            self._start(r.tcp_request, r.control_request)

    def close(self) -> None:
        """stop() and remove the temporary directory (and the flash file if it lives there)."""
        self.stop()
        if self.clock.lockstep:
            clocks.unregister(self.clock)
        self.resource.remove()
