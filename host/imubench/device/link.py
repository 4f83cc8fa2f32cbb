"""Host link and device client: talk to an imubench device through any pyserial URL.

    with Device.open("socket://127.0.0.1:5555") as dev:     # or /dev/ttyUSB0, rfc2217://...
        print(dev.info())
        dev.start_stream(rate_hz=1000)
        block = dev.read(n_samples=5000)                     # decoder.SampleBlock (numpy)
        dev.stop_stream()

A reader thread owns the port's input: it feeds the streaming decoder, matches replies to
requests by request id, and (optionally) appends every received byte to a capture file
as it arrives, so a crash loses nothing that reached the host. Every command gets exactly
one ack; a missing ack is retried with the same request id (the device answers a repeated
id without running the command twice), then raises LinkTimeout. An ack whose data frame
(info, params_readback, stats, self_test_result) was damaged is retried the same way.
A nack raises DeviceError.

Every wait here (an ack, samples, a reboot's info, read's duration) goes through the link's
clock (imubench.device.clock): the wall clock for a real port, device time for a virtual
device in lockstep, whose waits grant it the time they wait for. Timeouts are then device
seconds.
"""
from __future__ import annotations

import os
import select
import socket
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import BinaryIO, Iterator

import serial

from imubench.device import clock as clocks
from imubench.wire import frame as P
from imubench.wire.decoder import DecodedFrame, SampleBlock, StreamDecoder
from imubench.wire.protocol_gen import (
    SAVE_UNCHANGED_FLAG,
    Ack,
    ClearParams,
    Error,
    FaultEvent,
    GetInfo,
    GetParams,
    GetStats,
    Info,
    MsgType,
    Params,
    ParamsReadback,
    ParamsWhich,
    Ping,
    Reboot,
    SaveParams,
    SelfTest,
    SelfTestResult,
    SetParams,
    StartStream,
    Stats,
    StopStream,
    StreamMode,
)

PORT_ENV = "IMUBENCH_PORT"
DEFAULT_BAUD = 2_000_000   # the boards' default (protocol/SPEC.md, link budget)


class LinkError(IOError):
    """The link itself failed (port closed, device gone)."""


class NoPort(LinkError):
    """No port was given (no --port, no IMUBENCH_PORT): a usage error, not a link failure."""


class NewerFirmware(LinkError):
    """The device answered with a well-formed info (its CRC good) holding a value this host's
    protocol definition does not have: a newer firmware, not a damaged link."""

    def __init__(self, url: str, field: str, value, kind: str, allowed=None):
        what = (f"unknown bits 0x{value & ~allowed & 0xFFFFFFFF:X} in {field}" if kind == "flags" else
                f"unknown value {value} for {field}")
        super().__init__(f"newer firmware: {what} (the info from {url} is intact; this imubench does not "
                         "know that value)")
        self.field, self.value = field, value


class CaptureError(LinkError):
    """The capture file could not be written (a full disk, a removed drive): the stream stops
    rather than go on with bytes that are not on disk. `errno` is the OS error's."""

    def __init__(self, path, err: OSError):
        super().__init__(f"cannot write the capture file {path}: {err.strerror or err}")
        self.errno = err.errno
        self.filename = str(path)


class ProtocolVersionError(LinkError):
    """The device sends intact frames of another protocol version: nothing it says can be read."""

    def __init__(self, url: str, device_version: int):
        from imubench import __version__
        newer = device_version > P.PROTOCOL_VERSION
        super().__init__(
            f"the device on {url} speaks protocol version {device_version}, this imubench {__version__} "
            f"speaks version {P.PROTOCOL_VERSION}: "
            + ("install a newer imubench, or flash this one's firmware (imubench flash)" if newer else
               "flash this imubench's firmware onto it (imubench flash), or use the imubench it was built with"))
        self.device_version = device_version
        self.url = url


class LinkTimeout(TimeoutError):
    """No ack arrived for a command after all retries."""


class DeviceError(RuntimeError):
    """The device refused a command (a nack): `code` says why."""

    def __init__(self, command: int, code: int, detail: int = 0):
        try:
            cname = MsgType(command).name.lower()
        except ValueError:
            cname = f"0x{command:02X}"
        try:
            self.code = Error(code)
            ename = self.code.name
        except ValueError:
            self.code = code
            ename = f"error {code}"
        super().__init__(f"device refused {cname}: {ename} (detail {detail})")
        self.command = command
        self.detail = detail


def ports_matching(regex: str) -> list[str]:
    """The serial ports whose description matches regex, as pyserial's hwgrep:// sees them
    (serial.tools.list_ports.grep); re.error when regex is not a regular expression."""
    from serial.tools import list_ports
    return [p.device for p in list_ports.grep(regex)]


def resolve_port(url: str | None) -> str:
    url = url or os.environ.get(PORT_ENV)
    if not url:
        raise NoPort(f"no port given; pass --port URL or set {PORT_ENV} "
                        "(a device path like /dev/ttyUSB0, or socket://HOST:PORT, rfc2217://...)")
    check_network_url(url)
    return url


def check_network_url(url: str) -> None:
    """A socket:// or rfc2217:// URL must name a host and a numeric TCP port: refused here in
    one line (pyserial would fail with a comparison error on a missing port)."""
    from urllib.parse import urlsplit
    scheme = url.partition("://")[0].lower() if "://" in url else ""
    if scheme not in ("socket", "rfc2217"):
        return
    example = f"{scheme}://localhost:5555"
    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError:
        raise NoPort(f"{url}: the port is not a number from 1 to 65535; give {scheme}://HOST:PORT "
                     f"(e.g. {example})") from None
    if port is None:
        raise NoPort(f"{url} names no TCP port; give {scheme}://HOST:PORT (e.g. {example})")
    if not 0 < port < 65536:
        raise NoPort(f"{url}: port {port} is not from 1 to 65535; give {scheme}://HOST:PORT (e.g. {example})")


@dataclass
class _Pending:
    command: int
    ack: Ack | None = None
    data: list | None = None


class Link:
    """Serial endpoint + reader thread + decoder. Use Device for the command API."""

    def __init__(self, url: str | None = None, baudrate: int = DEFAULT_BAUD, capture: BinaryIO | None = None):
        self.url = resolve_port(url)
        try:
            # non-blocking reads: the reader thread waits in select() on the port's descriptor
            # and then takes everything available at once (pyserial's in_waiting is only
            # 0 or 1 for socket:// URLs, so it cannot size the reads)
            self.port = serial.serial_for_url(self.url, baudrate=baudrate, timeout=0, write_timeout=2.0)
        except (serial.SerialException, ValueError, OSError) as e:
            raise LinkError(f"cannot open {self.url}: {e}") from e
        self.decoder = StreamDecoder()
        self.capture = capture
        self._lock = threading.Lock()
        self._cond = threading.Condition(self._lock)
        self._pending: dict[int, _Pending] = {}
        self.clock = clocks.for_url(self.url)     # wall clock, or a lockstep device's time
        self._next_id = int.from_bytes(os.urandom(2), "little") % 0xFFFF + 1   # SPEC.md: random start
        self.bytes_in = 0       # bytes read from the port (lockstep: every grant waits for its bytes)
        self.bytes_out = 0      # bytes written to it
        self.fault_events: deque[tuple[float, FaultEvent]] = deque(maxlen=1000)
        self.boot_infos: deque[Info] = deque(maxlen=10)
        self.last_stats: Stats | None = None
        self.error: BaseException | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._reader, name=f"imubench-link {self.url}", daemon=True)
        if self.clock.lockstep:
            self.clock.attach(self)
        self._thread.start()
        self._write(b"\0")     # ends any partial frame the device holds (protocol/SPEC.md, Framing)

    # ----------------------------------------------------------------- reading
    def _wait_readable(self) -> None:
        """Block until the port may have data (or 50 ms pass)."""
        try:
            fd = self.port.fileno()
        except (AttributeError, OSError, ValueError, NotImplementedError):
            fd = None
        if fd is None:
            time.sleep(0.002)       # URL handlers without a descriptor (rfc2217, loop)
        else:
            select.select([fd], [], [], 0.05)

    def _reader(self) -> None:
        port = self.port
        try:
            while not self._stop.is_set():
                data = port.read(1 << 16)
                if not data:
                    self._wait_readable()
                    continue
                if self.capture is not None:
                    try:
                        self.capture.write(data)
                        self.capture.flush()
                    except OSError as e:
                        self.error = CaptureError(getattr(self.capture, "name", "?"), e)
                        break
                with self._cond:
                    self.bytes_in += len(data)
                    frames = self.decoder.feed(data)
                    if self.decoder.foreign_version is not None:
                        # another protocol version: say so at once, before any timeout or
                        # half-understood reply (every request now fails with this error)
                        self.error = ProtocolVersionError(self.url, self.decoder.foreign_version)
                        break
                    for f in frames:
                        self._dispatch(f)
                    self._cond.notify_all()
        except (serial.SerialException, OSError, TypeError, AttributeError) as e:
            if not self._stop.is_set():
                self.error = e
        finally:
            with self._cond:
                self._cond.notify_all()

    def _failure(self) -> LinkError:
        """The error to raise after the reader thread stopped on self.error."""
        if isinstance(self.error, LinkError):
            return self.error
        return LinkError(f"link to {self.url} failed: {self.error}")

    def _dispatch(self, f: DecodedFrame) -> None:
        m = f.msg
        if f.type == MsgType.ACK:
            p = self._pending.get(m.request_id)
            if p is not None and p.command == m.command:
                p.ack = m
            return
        rid = getattr(m, "request_id", 0)
        if rid and rid in self._pending:
            self._pending[rid].data.append(m)
            return
        if f.type == MsgType.FAULT_EVENT:
            self.fault_events.append((self.clock.now(), m))
        elif f.type == MsgType.INFO:            # unsolicited: the device (re)booted
            self.boot_infos.append(m)        # the decoder itself forgot the streams on it
        elif f.type == MsgType.STATS:
            self.last_stats = m

    # ---------------------------------------------------------------- requests
    def request(self, msg, timeout: float = 1.0, retries: int = 2, expect: type | None = None) -> tuple[Ack, list]:
        """Send a command, wait for its ack; returns (ack, data messages). Raises
        DeviceError on a nack, LinkTimeout when no ack came after 1 + retries sends.

        With `expect` (the data message class the command returns), an ack that arrives
        without that message (its frame was damaged on the way and rejected) counts like a
        missing ack: the same frame is sent again at once, same request id, and the device
        resends both stored frames (protocol/SPEC.md, Retries). After 1 + retries sends
        without the data, LinkError."""
        d = P.MESSAGES_BY_NAME[P.message_name(msg)]
        payload = P.encode_message(msg)
        with self._cond:
            if self.clock.lockstep:
                rid = self.clock.request_id()               # the same ids on every run
            else:
                rid = self._next_id
                self._next_id = self._next_id % 0xFFFF + 1     # 1..65535; 0 means unsolicited
            pend = self._pending[rid] = _Pending(d.id, None, [])
        frame = P.build_frame(d.id, payload, rid, int(self.clock.now() * 1e6) & 0xFFFFFFFF)
        data_lost = 0
        try:
            for _attempt in range(retries + 1):
                self._write(frame)
                self.clock.wait_for(lambda: pend.ack is not None or self.error is not None, timeout, self._cond)
                with self._cond:
                    if self.error is not None:
                        raise self._failure()
                    if pend.ack is not None:
                        ack = pend.ack
                        if ack.error != Error.OK:
                            raise DeviceError(ack.command, ack.error, ack.value)
                        if expect is None or any(isinstance(m, expect) for m in pend.data):
                            return ack, pend.data
                        newer = self.decoder.refused_info if expect is Info else None
                        if newer is not None and newer[0] == rid:
                            raise NewerFirmware(self.url, *newer[1:])
                        pend.ack = None          # acked, but its data frame was lost: ask again
                        data_lost += 1
            if data_lost:
                raise LinkError(f"{d.name} (request {rid}) to {self.url}: the device acked "
                                f"without a readable {expect.__name__} {data_lost} of {retries + 1} "
                                "times (a damaged link?)")
            raise LinkTimeout(f"no answer to {d.name} (request {rid}) from {self.url} after "
                              f"{retries + 1} tries of {timeout:g} s")
        finally:
            with self._cond:
                self._pending.pop(rid, None)

    def _write(self, data: bytes) -> None:
        try:
            self.port.write(data)
            self.port.flush()
        except (serial.SerialException, OSError) as e:
            raise LinkError(f"write to {self.url} failed: {e}") from e
        self.bytes_out += len(data)

    def wait_bytes_in(self, n: int, guard_wall_s: float) -> None:
        """Lockstep: wait until n bytes were read from the port since it was opened (the
        device has sent them; the wall-clock guard is against a reader that died)."""
        deadline = time.monotonic() + guard_wall_s
        with self._cond:
            while self.bytes_in < n and self.error is None and self._thread.is_alive():
                left = deadline - time.monotonic()
                if left <= 0:
                    raise LinkError(f"{self.url}: the virtual device sent {n} bytes, {self.bytes_in} arrived "
                                    f"within {guard_wall_s:g} s")
                self._cond.wait(min(left, 0.5))

    # ----------------------------------------------------------------- samples
    def take_samples(self, calibrated: bool = False) -> SampleBlock | None:
        with self._cond:
            return self.decoder.take_samples(calibrated)

    def discard_samples(self) -> None:
        """Drop samples not yet taken and forget sequence state (a new stream starts)."""
        with self._cond:
            self.decoder.take_samples(False)
            self.decoder.take_samples(True)
            self.decoder.reset_sequence()

    def wait_samples(self, n: int, calibrated: bool, timeout: float, step_s: float | None = None) -> None:
        """Wait until n samples are buffered (or timeout on the link's clock; lockstep: grants of
        step_s device seconds)."""
        self.clock.wait_for(lambda: self.decoder.pending_samples(calibrated) >= n or self.error is not None,
                            timeout, self._cond, step_s=step_s)

    def close(self) -> None:
        if self.clock.lockstep:
            self.clock.detach(self)
        self._stop.set()
        self._thread.join(timeout=2.0)
        try:
            _close_socket_port(self.port)
            self.port.close()
        except Exception:  # noqa: BLE001 - closing a dead port must not hide the real error
            pass


def _close_socket_port(port) -> None:
    """Close a socket:// port without pyserial's pause. pyserial 3.5's socket handler sleeps
    0.3 s in every close() "in case of quick reconnects"; our devices need no such pause (the
    virtual device takes a new client at once, and a board on a serial-to-TCP bridge is the
    bridge's business), so a command that opens and closes a port should not pay it each time.
    The socket is shut down and closed here, as pyserial would, and the port marked closed, so
    that its own close() has nothing left to do."""
    sock = getattr(port, "_socket", None)
    if sock is None or not type(port).__module__.endswith("protocol_socket"):
        return
    try:
        sock.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass
    sock.close()
    port._socket = None
    port.is_open = False


class Device:
    """The device's command API on top of a Link."""

    def __init__(self, url: str | None = None, baudrate: int = DEFAULT_BAUD, timeout: float = 1.0,
                 retries: int = 2, capture: BinaryIO | None = None):
        self.link = Link(url, baudrate, capture)
        self.timeout = timeout
        self.retries = retries
        self._stream_mode: StreamMode | None = None
        self._rate_hz = 1000
        self.last_save_unchanged = False      # the last save_params found the block already stored
        self._leftover: dict[bool, SampleBlock] = {}

    @classmethod
    def open(cls, url: str | None = None, **kw) -> "Device":
        return cls(url, **kw)

    @property
    def clock(self):
        """The clock the host waits by (imubench.device.clock): the wall clock, or the device
        time of a lockstep virtual device."""
        return self.link.clock

    def __enter__(self) -> "Device":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self.link.close()

    def _req(self, msg, timeout: float | None = None, expect: type | None = None):
        return self.link.request(msg, timeout or self.timeout, self.retries, expect)

    def _one(self, msg, cls, timeout: float | None = None):
        """Send msg and return the cls data message its ack comes with (retried when the
        ack arrives but the data frame was damaged)."""
        for m in self._req(msg, timeout, expect=cls)[1]:
            if isinstance(m, cls):
                return m
        raise LinkError(f"the device acked without sending {cls.__name__}")   # not reached

    # ---------------------------------------------------------------- commands
    def ping(self, nonce: int = 0x1B3C5D7E) -> float:
        """Round trip time in seconds; checks the echoed nonce."""
        t0 = time.perf_counter()
        ack, _ = self._req(Ping(nonce=nonce))
        if ack.value != nonce:
            raise LinkError(f"ping echoed 0x{ack.value:08X}, sent 0x{nonce:08X}")
        return time.perf_counter() - t0

    def info(self) -> Info:
        return self._one(GetInfo(), Info)

    def start_stream(self, rate_hz: int = 1000, calibrated: bool = False, batch: int = 0,
                     accel_range_g: int = 0) -> int:
        """Start streaming; returns the batch size the device chose."""
        mode = StreamMode.CALIBRATED if calibrated else StreamMode.RAW
        self.link.discard_samples()
        self._leftover.clear()
        ack, _ = self._req(StartStream(rate_hz=rate_hz, mode=mode, batch=batch, accel_range_g=accel_range_g))
        self._stream_mode = mode
        self._rate_hz = max(int(rate_hz), 1)
        return ack.value

    def stop_stream(self) -> None:
        self._req(StopStream())
        self._stream_mode = None

    def set_params(self, params: Params) -> None:
        self._req(SetParams(params=params))

    def get_params(self, which: ParamsWhich = ParamsWhich.ACTIVE) -> ParamsReadback:
        return self._one(GetParams(which=which), ParamsReadback)

    def save_params(self) -> int:
        """Write the active parameters to flash; returns the stored generation. When the block
        was already stored the device writes nothing (no flash wear) and says so: then
        `last_save_unchanged` is True and the generation is the one it had."""
        value = self._req(SaveParams(), timeout=max(self.timeout, 3.0))[0].value
        self.last_save_unchanged = bool(value & SAVE_UNCHANGED_FLAG)
        return value & ~SAVE_UNCHANGED_FLAG

    def clear_params(self) -> None:
        self._req(ClearParams(), timeout=max(self.timeout, 3.0))

    def self_test(self) -> SelfTestResult:
        return self._one(SelfTest(), SelfTestResult, timeout=max(self.timeout, 5.0))

    def stats(self, reset: bool = False) -> Stats:
        return self._one(GetStats(reset=int(reset)), Stats)

    def reboot(self, wait_s: float = 5.0) -> Info | None:
        """Reboot; with wait_s > 0, wait for the boot info and return it."""
        n_before = len(self.link.boot_infos)
        self._req(Reboot())
        self._stream_mode = None
        if wait_s <= 0:
            return None
        if self.clock.wait_for(lambda: len(self.link.boot_infos) > n_before, wait_s, self.link._cond):
            return self.link.boot_infos[-1]
        raise LinkTimeout(f"device did not announce itself within {wait_s} s of reboot")

    # ----------------------------------------------------------------- samples
    def discard_buffered(self) -> None:
        """Drop every sample received but not yet read (e.g. after changing the board's
        attitude, to read only what comes after). The stream keeps running."""
        with self.link._cond:
            self.link.decoder.take_samples(False)
            self.link.decoder.take_samples(True)
        self._leftover.clear()

    def read(self, n_samples: int | None = None, duration_s: float | None = None,
             calibrated: bool | None = None, timeout: float | None = None) -> SampleBlock:
        """Collect samples of the running stream: n_samples of them, or for duration_s on the
        link's clock (host time; device time for a lockstep virtual device). Raises LinkTimeout
        if they do not arrive within timeout (lockstep: device seconds beyond the time the
        samples take at the stream's rate)."""
        cal = (self._stream_mode == StreamMode.CALIBRATED) if calibrated is None else calibrated
        blocks, have = [], 0
        left = self._leftover.pop(cal, None)
        if left is not None:
            blocks.append(left)
            have = len(left)
        if n_samples is None and duration_s is None:
            raise ValueError("give n_samples or duration_s")
        clock = self.clock
        t0 = clock.now()
        t_end = t0 + (duration_s if duration_s is not None else 0)
        limit = t0 + (timeout if timeout is not None else
                      (duration_s or 0) + 5.0 + (n_samples or 0) / 500.0)
        if clock.lockstep:      # device time: the timeout is on top of what the samples take
            limit += (duration_s or 0) + (n_samples or 0) / self._rate_hz
        while True:
            need = (n_samples - have) if n_samples is not None else 1
            step = None
            if clock.lockstep:      # grant what the samples still missing take (device time)
                step = (max(t_end - clock.now(), 0.001) if n_samples is None else
                        min(max(need / self._rate_hz, 0.001) + 0.002, 1.0))
            self.link.wait_samples(max(need, 1), cal, timeout=0.05 if step is None else step, step_s=step)
            b = self.link.take_samples(cal)
            if b is not None and len(b):
                blocks.append(b)
                have += len(b)
            if self.link.error is not None:
                raise self.link._failure()
            now = clock.now()
            # duration_s of host time, but at least one block: a device whose batches come in
            # bursts (a USB-serial latency timer, a network hop, an emulated device running
            # near real time) can leave a short window empty; that is not a missing stream
            if (n_samples is not None and have >= n_samples) or (n_samples is None and now >= t_end and blocks):
                break
            if now > limit:
                if not blocks:
                    raise LinkTimeout("no samples arrived")
                raise LinkTimeout(f"{have} of {n_samples} samples arrived before the timeout")
        out = SampleBlock.concat(blocks)
        if n_samples is not None and len(out) > n_samples:
            self._leftover[cal] = out[n_samples:]   # kept for the next read
            out = out[:n_samples]
        return out

    def stream(self, calibrated: bool | None = None, poll_s: float = 0.05) -> Iterator[SampleBlock]:
        """Yield sample blocks as they arrive, until the caller stops iterating. Against a
        lockstep virtual device each wait grants poll_s of device time (a block per poll_s)."""
        step = poll_s if self.clock.lockstep else None
        cal = (self._stream_mode == StreamMode.CALIBRATED) if calibrated is None else calibrated
        left = self._leftover.pop(cal, None)
        if left is not None:
            yield left
        while True:
            self.link.wait_samples(1, cal, timeout=poll_s, step_s=step)
            if self.link.error is not None:
                raise self.link._failure()
            b = self.link.take_samples(cal)
            if b is not None and len(b):
                yield b

