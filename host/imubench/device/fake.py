"""A device emulated in Python behind a real pseudo-terminal.

It speaks the whole command set of protocol/SPEC.md and streams synthetic samples (a
still board, gravity along a chosen direction, white noise at the parts' datasheet
densities), so the host link, the CLI and the demo can be exercised end to end through a
real serial port without hardware. It is NOT the virtual device (the firmware core built
for Linux with register-level sensor models); it exists for host-side tests, with knobs
to misbehave: drop acks, corrupt bytes, refuse flash writes.
"""
from __future__ import annotations

import errno
import os
import select
import threading
import time
import tty

import numpy as np

from imubench.parts_gen import PARTS
from imubench.units import G0_MPS2
from imubench.wire import frame as P
from imubench.wire import params as PR
from imubench.wire.protocol_gen import (
    Ack,
    BatchHeader,
    Board,
    CalBatch,
    ClockSource,
    Error,
    Info,
    MsgType,
    Params,
    ParamSource,
    ParamsReadback,
    RawBatch,
    SelfTestResult,
    Stats,
    StreamMode,
    StreamState,
)

ACCEL, GYRO = PARTS["adxl355"], PARTS["adxrs450"]   # the fake board's parts (protocol/parts.toml)

ACCEL_NOISE_G_RTHZ = 22.5e-6
GYRO_NOISE_DPS_RTHZ = 0.015
FW_VERSION = (0, 1, 0)


class FakeDevice:
    """Start with `with FakeDevice() as dev:`; connect a client to `dev.port_url`."""

    def __init__(self, seed: int = 1, speed: float = 1.0, gravity_board=(0.0, 0.0, 1.0)):
        self.rng = np.random.default_rng(seed)
        self.speed = speed
        self.gravity_board = np.asarray(gravity_board, dtype=np.float64)
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        os.set_blocking(self.master, False)
        self.port_url = os.ttyname(self.slave)
        # misbehaviour knobs for tests
        self.drop_acks = 0            # swallow the next N acks (the client must retry)
        self.damage_data = 0          # flip a byte in the next N data frames (info, readback...)
        self.flash_fails = False      # save_params fails with FLASH_ERROR
        self.commands_executed: list[int] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.flash: tuple[Params, int] | None = None     # (params, generation)
        self._boot()
        self._thread = threading.Thread(target=self._run, name="fakedev", daemon=True)

    def _boot(self) -> None:
        self.t0 = time.monotonic()
        self.seq = 0
        if self.flash:      # boot loads the stored block, as the firmware does
            self.active, self.param_source = self.flash[0], ParamSource.FLASH
        else:
            self.active, self.param_source = PR.identity(), ParamSource.FACTORY
        self.streaming: StreamMode | None = None
        self.rate_hz = 0
        self.batch = 0
        self.range_g = 2
        self.sample_index = 0
        self.stream_t0 = 0.0
        self.last_rid: int | None = None
        self.last_command: tuple | None = None   # (request id, type, payload) of the last command run
        self.last_reply: list[bytes] = []
        self.stats = dict(frames_sent=0, frames_dropped=0, samples_produced=0, samples_dropped=0,
                          spi_errors=0, sensor_faults=0, bad_commands=0, rx_frame_errors=0)
        self._rx = bytearray()

    # ------------------------------------------------------------ lifecycle
    def __enter__(self) -> "FakeDevice":
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def start(self) -> None:
        self._thread.start()
        self._send(b"\0" + self._frame(self._info(0)))

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass

    def device_time_us(self) -> int:
        return int((time.monotonic() - self.t0) * self.speed * 1e6)

    # ------------------------------------------------------------- output
    def _frame(self, msg, records=None) -> bytes:
        f = P.encode(msg, self.seq, self.device_time_us() & 0xFFFFFFFF, records=records)
        self.seq = (self.seq + 1) & 0xFFFF
        return f

    def _send(self, frame: bytes) -> bool:
        try:
            n = os.write(self.master, frame)
        except OSError as e:
            if e.errno in (errno.EAGAIN, errno.EIO):
                self.stats["frames_dropped"] += 1
                return False
            raise
        if n < len(frame):       # pty buffer full: the rest goes when there is room
            rest = memoryview(frame)[n:]
            deadline = time.monotonic() + 0.5
            while len(rest) and time.monotonic() < deadline:
                try:
                    rest = rest[os.write(self.master, rest):]
                except BlockingIOError:
                    time.sleep(0.001)
        self.stats["frames_sent"] += 1
        return True

    # -------------------------------------------------------------- loop
    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                r, _, _ = select.select([self.master], [], [], 0.002)
            except (OSError, ValueError):
                return
            if r:
                try:
                    data = os.read(self.master, 4096)
                except BlockingIOError:
                    data = b""
                except OSError:
                    data = b""       # no client attached yet (EIO): keep serving
                    time.sleep(0.01)
                self._rx += data
                while True:
                    i = self._rx.find(0)
                    if i < 0:
                        if len(self._rx) > P.MAX_ENCODED:
                            self._rx.clear()
                            self.stats["rx_frame_errors"] += 1
                        break
                    chunk = bytes(self._rx[:i])
                    del self._rx[:i + 1]
                    if chunk:
                        with self._lock:
                            self._handle(chunk)
            with self._lock:
                self._stream_step()

    def _handle(self, chunk: bytes) -> None:
        try:
            f = P.parse_frame(chunk)
        except P.ProtocolError as e:
            if e.reason is P.FrameError.BAD_VERSION:
                seq = int.from_bytes(P.cobs.decode(chunk)[2:4], "little")
                self._reply_all(seq, 0, [], Error.BAD_VERSION)
            elif e.reason in (P.FrameError.UNKNOWN_TYPE, P.FrameError.BAD_LENGTH):
                raw = P.cobs.decode(chunk)
                err = Error.UNKNOWN_COMMAND if e.reason is P.FrameError.UNKNOWN_TYPE else Error.BAD_LENGTH
                self._reply_all(int.from_bytes(raw[2:4], "little"), raw[1], [], err)
            elif e.reason in P.VALUE_ERRORS.values():   # readable, a field out of its definition
                raw = P.cobs.decode(chunk)
                self._reply_all(int.from_bytes(raw[2:4], "little"), raw[1], [], Error.BAD_ARGUMENT)
            else:
                self.stats["rx_frame_errors"] += 1
            return
        if f.type not in P.gen.COMMANDS:
            self._reply_all(f.seq, f.type, [], Error.UNKNOWN_COMMAND)
            return
        command = (f.seq, f.type, bytes(f.payload))
        if command == self.last_command and self.last_reply:
            for fr in self.last_reply:     # a retry (same id, type, payload): answer again, do not run twice
                self._maybe_send_ack(fr)
            return
        msg = P.decode_message(f.type, f.payload)
        self.commands_executed.append(f.type)
        data, err, value = self._execute(f.type, msg, f.seq)
        self._reply_all(f.seq, f.type, data, err, value)
        self.last_command = command
        if f.type == MsgType.REBOOT and err == Error.OK:
            self._boot()
            self._send(b"\0" + self._frame(self._info(0)))

    def _reply_all(self, rid: int, command: int, data: list, err: Error, value: int = 0) -> None:
        frames = [self._frame(m) for m in data]
        frames.append(self._frame(Ack(request_id=rid, command=command, error=int(err), value=value)))
        if err != Error.OK:
            self.stats["bad_commands"] += 1
        self.last_rid, self.last_reply = rid, frames
        self.last_command = None           # set by the caller once it ran a command
        for fr in frames:
            self._maybe_send_ack(fr)

    def _maybe_send_ack(self, frame: bytes) -> None:
        is_ack = P.parse_frame(frame[:-1]).type == MsgType.ACK
        if self.drop_acks and is_ack:
            self.drop_acks -= 1
            return
        if self.damage_data and not is_ack:
            self.damage_data -= 1
            frame = frame[:3] + bytes([frame[3] ^ 0x40 or 0x40]) + frame[4:]   # CRC now fails
        self._send(frame)

    # ----------------------------------------------------------- commands
    def _info(self, rid: int) -> Info:
        return Info(
            request_id=rid, protocol_version=P.PROTOCOL_VERSION, board=Board.UNKNOWN, fw_version=FW_VERSION,
            clock_source=ClockSource.NONE, fw_build="python-fake", mcu_uid=tuple(range(0xF0, 0xFC)),
            sensors_present=0b1111, accel_range_g=self.range_g, parts=(ACCEL.id,) + (GYRO.id,) * 3,
            accel_ids=(0xAD, 0x1D, 0xED, 0x01),
            gyro_pid=(0x5201,) * 3, gyro_sn=(0x1000001, 0x1000002, 0x1000003),
            stream_state={None: StreamState.STOPPED, StreamMode.RAW: StreamState.RAW,
                          StreamMode.CALIBRATED: StreamState.CALIBRATED}[self.streaming],
            param_source=self.param_source, stream_rate_hz=self.rate_hz, max_rate_hz=4000,
            param_block_version=P.gen.PARAM_BLOCK_VERSION,
            param_generation=self.flash[1] if self.flash else 0, baud=0,
            uptime_ms=self.device_time_us() // 1000 & 0xFFFFFFFF)

    def _execute(self, t: int, m, rid: int):
        T = MsgType
        if t == T.PING:
            return [], Error.OK, m.nonce
        if t == T.GET_INFO:
            return [self._info(rid)], Error.OK, 0
        if t == T.START_STREAM:
            if m.rate_hz not in P.gen.STREAM_RATES_HZ or m.mode not in (0, 1) \
                    or m.accel_range_g not in (0, *(r.full_scale for r in ACCEL.ranges)):
                return [], Error.BAD_ARGUMENT, 0
            maxb = 16 if m.mode == 0 else 8
            if m.batch > maxb:
                return [], Error.BAD_ARGUMENT, 0
            self.rate_hz = m.rate_hz
            self.batch = m.batch or max(1, min(maxb, m.rate_hz // 250))
            self.range_g = m.accel_range_g or self.range_g
            self.streaming = StreamMode(m.mode)
            self.sample_index = 0
            self.stream_t0 = time.monotonic()
            return [], Error.OK, self.batch
        if t == T.STOP_STREAM:
            self.streaming = None
            return [], Error.OK, 0
        if t == T.SET_PARAMS:
            try:
                PR.validate(m.params)
            except PR.InvalidParams as e:
                return [], e.code, 0
            self.active = m.params
            self.param_source = ParamSource.UNSAVED
            return [], Error.OK, 0
        if t == T.GET_PARAMS:
            if m.which == 0:
                rb = ParamsReadback(request_id=rid, which=0, source=self.param_source,
                                    generation=self.flash[1] if self.flash else 0, params=self.active)
            elif m.which == 1:
                p, g = self.flash if self.flash else (PR.identity(), 0)
                rb = ParamsReadback(request_id=rid, which=1, source=ParamSource.FLASH if self.flash else ParamSource.FACTORY,
                                    generation=g, params=p)
            else:
                return [], Error.BAD_ARGUMENT, 0
            return [rb], Error.OK, 0
        if t in (T.SAVE_PARAMS, T.CLEAR_PARAMS, T.SELF_TEST) and self.streaming is not None:
            return [], Error.STREAMING, 0
        if t == T.SAVE_PARAMS:
            if self.flash_fails:
                return [], Error.FLASH_ERROR, 0
            gen = (self.flash[1] if self.flash else 0) + 1
            self.flash = (self.active, gen)
            self.param_source = ParamSource.FLASH
            return [], Error.OK, gen
        if t == T.CLEAR_PARAMS:
            self.active = PR.identity()
            self.flash = None
            self.param_source = ParamSource.FACTORY
            return [], Error.OK, 0
        if t == T.REBOOT:
            return [], Error.OK, 0
        if t == T.SELF_TEST:
            r = SelfTestResult(request_id=rid, passed=0b1111, tested=0b1111,
                               accel_delta_counts=(76800, 76800, 384000), gyro_chk_faults=(0xFE,) * 3)
            return [r], Error.OK, 0
        if t == T.GET_STATS:
            s = Stats(request_id=rid, uptime_ms=self.device_time_us() // 1000 & 0xFFFFFFFF, **self.stats)
            if m.reset:
                for k in self.stats:
                    self.stats[k] = 0
            return [s], Error.OK, 0
        return [], Error.UNKNOWN_COMMAND, 0

    # ------------------------------------------------------------ stream
    def _stream_step(self) -> None:
        if self.streaming is None:
            return
        due = int((time.monotonic() - self.stream_t0) * self.speed * self.rate_hz)
        while due - self.sample_index >= self.batch:
            self._send_batch(self.batch)

    def _send_batch(self, n: int) -> None:
        period_us = 1_000_000 // self.rate_hz
        g = self.gravity_board / np.linalg.norm(self.gravity_board)
        lsb = ACCEL.lsb_per_unit(self.range_g)
        a_sig = ACCEL_NOISE_G_RTHZ * np.sqrt(self.rate_hz)
        w_sig = GYRO_NOISE_DPS_RTHZ * np.sqrt(self.rate_hz)
        accel_g = g + self.rng.normal(0.0, a_sig, (n, 3))
        rate_dps = self.rng.normal(0.0, w_sig, (n, 3))
        hdr = BatchHeader(sample_index=self.sample_index & 0xFFFFFFFF, period_us=period_us, count=n,
                          accel_temp_counts=1885, accel_range_g=self.range_g, gyro_temp_counts=(-100, -100, -100))
        ts_first = int(self.sample_index * period_us)
        if self.streaming == StreamMode.RAW:
            counts = np.clip(np.round(accel_g * lsb), -(1 << 19), (1 << 19) - 1).astype(np.int64)
            recs = dict(accel_x_counts=counts[:, 0], accel_y_counts=counts[:, 1], accel_z_counts=counts[:, 2],
                        status=np.zeros(n, np.uint8),
                        gyro_counts=np.clip(np.round(rate_dps * GYRO.lsb_per_unit()), -32768, 32767).astype(np.int16))
            msg = RawBatch(header=hdr)
        else:
            acc = PR.correct(PR.accel(self.active), accel_g * G0_MPS2)
            gyr = PR.correct(PR.gyro(self.active), np.deg2rad(rate_dps), accel_mps2=acc)
            recs = dict(accel_mps2=acc.astype(np.float32), rate_rad_s=gyr.astype(np.float32), status=np.zeros(n, np.uint8))
            msg = CalBatch(header=hdr)
        f = P.encode(msg, self.seq, ts_first & 0xFFFFFFFF, records=recs)
        self.seq = (self.seq + 1) & 0xFFFF
        self.sample_index += n
        self.stats["samples_produced"] += n
        if not self._send(f):
            self.stats["samples_dropped"] += n
