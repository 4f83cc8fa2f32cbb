"""The STM32 firmware images under qemu-system-arm (imubench.device.qemu), both boards:
stm32vldiscovery (F1 board code, build/arm/qemu-f1) and netduinoplus2 (F4, build/arm/qemu-f4).

Under QEMU nothing answers on SPI (reads 0x00), so the firmware must find every sensor
missing, say so (info, fault events, batch flags, sample status) and keep serving commands.
Flash writes are dropped by QEMU, so save_params must fail cleanly (FLASH_ERROR); a parameter
page preloaded with -device loader (built by imubench.wire.paramstore) must be validated and
applied at boot, a corrupted one rejected.

These tests never skip: `make firmware` installs the toolchain and QEMU (as root); when
qemu-system-arm is missing QemuBoard raises and the tests fail.

The last part checks imubench.wire.paramstore against the C parameter store itself
(firmware/core/param_store.c compiled for the host with a small checker program).
"""
from __future__ import annotations

import math
import socket
import struct
import subprocess
import time
from pathlib import Path

import pytest
from conftest import ROOT
from imubench.device.link import Device, DeviceError
from imubench.device.qemu import QemuBoard, build_firmware
from imubench.wire import frame as P
from imubench.wire import paramstore as PS
from imubench.wire.protocol_gen import (
    Board,
    ClockSource,
    Error,
    FaultKind,
    MsgType,
    Params,
    ParamSource,
    ParamsWhich,
    StreamState,
)

BOARDS = {"f103": (Board.QEMU_F1, "qemu-f1"), "f4": (Board.QEMU_F4, "qemu-f4")}
ALL_MISSING = 0x0F


def params_bytes(p: Params) -> bytes:
    return Params.STRUCT.pack(*p.values())


def sample_params(seed: int = 1) -> Params:
    """A valid, non-trivial block whose floats are exact in binary32 (round trips bit-exact)."""
    k = seed * 0.0009765625  # 2^-10
    return Params(
        accel_m=(1.0 + k, 0.0078125, -0.00390625, 0.001953125, 1.0 - k, 0.0, 0.0, -0.0078125, 1.0 + 2 * k),
        accel_b_mps2=(0.125, -0.0625, 0.03125),
        gyro_m=(1.0 - k, 0.0, 0.00390625, 0.0, 1.0 + k, 0.0, -0.001953125, 0.0, 1.0),
        gyro_b_rad_s=(0.001953125, -0.0009765625, 0.00048828125),
        accel_bias_tc_mps2_per_c=(0.0009765625, 0.0, -0.0009765625),
        accel_scale_tc_per_c=(0.0001220703125, 0.0, 0.0),
        gyro_bias_tc_rad_s_per_c=(0.0, 0.00006103515625, 0.0),
        gyro_scale_tc_per_c=(0.0, 0.0, -0.0001220703125),
        accel_t_ref_c=23.5, gyro_t_ref_c=31.25,
        cal_time_unix_s=1_700_000_000 + seed, cal_id=0xC0FFEE00 + seed,
        accel_bias_tc2_mps2_per_c2=(2.0 ** -20, 0.0, -(2.0 ** -21)), gyro_bias_tc3_rad_s_per_c3=(0.0, 2.0 ** -30, 0.0),
        accel_t_min_c=-10, accel_t_max_c=60, gyro_t_min_c=5, gyro_t_max_c=70,
    )


@pytest.fixture(scope="session")
def firmware_built():
    build_firmware()


def wait_boot(dev: Device, timeout: float = 10.0):
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if dev.link.boot_infos:
            return dev.link.boot_infos[-1]
        time.sleep(0.01)
    raise AssertionError("no boot info from the device")


class Running:
    """A QEMU board plus what its first connection saw at boot."""

    def __init__(self, q: QemuBoard, boot_info, boot_faults):
        self.q, self.boot_info, self.boot_faults = q, boot_info, boot_faults

    def device(self, timeout: float = 1.0) -> Device:
        return Device.open(self.q.port_url, timeout=timeout, retries=2)


def start_board(board: str, page: bytes | None = None):
    q = QemuBoard(board, page).start()
    try:
        with Device.open(q.port_url, timeout=1.0, retries=2) as dev:
            info = wait_boot(dev)
            t_end = time.monotonic() + 3.0  # the boot fault events follow the boot info
            while len(dev.link.fault_events) < 4 and time.monotonic() < t_end:
                time.sleep(0.01)
            faults = [e for _, e in dev.link.fault_events]
        return Running(q, info, faults)
    except BaseException:
        q.close()
        raise


@pytest.fixture(scope="module", params=sorted(BOARDS))
def qemu(request, firmware_built):
    r = start_board(request.param)
    r.name = request.param
    yield r
    r.q.close()
    assert not r.q.alive()


@pytest.fixture
def dev(qemu):
    with qemu.device() as d:
        yield d


# ----------------------------------------------------------------- boot, info

def test_boot_info_and_ping(qemu, dev):
    board_id, _ = BOARDS[qemu.name]
    b = qemu.boot_info
    assert b.request_id == 0 and b.board == board_id
    assert dev.ping(nonce=0x5A5AA5A5) < 1.0
    info = dev.info()
    assert info.board == board_id
    assert info.clock_source == ClockSource.HSI
    assert info.sensors_present == 0
    assert info.accel_ids == (0, 0, 0, 0)             # as read: SPI with no slave reads 0
    assert info.gyro_pid == (0, 0, 0)
    assert info.fw_build and info.fw_build != "unknown"
    assert len(info.mcu_uid) == 12 and any(info.mcu_uid)
    assert info.baud == 2_000_000
    assert info.stream_state == StreamState.STOPPED
    assert info.param_source == ParamSource.FACTORY and info.param_generation == 0
    assert info.uptime_ms >= b.uptime_ms


def test_sensors_missing_reported_at_boot(qemu):
    missing = {e.sensor for e in qemu.boot_faults if e.kind == FaultKind.MISSING and e.active}
    assert missing == {0, 1, 2, 3}


# ----------------------------------------------------------------- streaming

@pytest.mark.parametrize("calibrated", [False, True])
def test_stream_flags_every_sample_bad(dev, calibrated):
    n_faults = len(dev.link.fault_events)
    batch = dev.start_stream(rate_hz=200, calibrated=calibrated)
    assert batch == 1
    block = dev.read(n_samples=60, timeout=10)
    dev.stop_stream()
    assert len(block) == 60
    assert (block.sensor_flags & ALL_MISSING == ALL_MISSING).all()
    assert (block.status & 0x0F == 0x0F).all()               # every sensor bad in every sample
    assert (block.sample_index[1:] >= block.sample_index[:-1]).all()
    if not calibrated:
        assert not block.accel_counts.any() and not block.gyro_counts.any()
    # the stream (re)announces the missing sensors
    new = [e for _, e in list(dev.link.fault_events)[n_faults:]]
    assert {e.sensor for e in new if e.kind == FaultKind.MISSING and e.active} == {0, 1, 2, 3}
    assert dev.info().stream_state == StreamState.STOPPED
    dev.ping()


def test_stream_batches_at_4khz_keep_serving_commands(dev):
    assert dev.start_stream(rate_hz=4000, batch=16) == 16
    block = dev.read(n_samples=800, timeout=10)
    assert dev.ping() < 1.0                                     # commands while streaming
    with pytest.raises(DeviceError) as e:
        dev.save_params()
    assert e.value.code == Error.STREAMING
    dev.stop_stream()
    assert (block.status & 0x0F == 0x0F).all()
    assert (block.sample_index >= 0).all()


# ----------------------------------------------------------------- parameters

def test_params_round_trip_bit_exact(dev):
    p = sample_params(3)
    dev.set_params(p)
    r = dev.get_params(ParamsWhich.ACTIVE)
    assert r.source == ParamSource.UNSAVED
    assert params_bytes(r.params) == params_bytes(p)
    assert dev.info().param_source == ParamSource.UNSAVED


def test_save_params_fails_cleanly_under_qemu(dev):
    p = sample_params(4)
    dev.set_params(p)
    with pytest.raises(DeviceError) as e:
        dev.save_params()
    assert e.value.code == Error.FLASH_ERROR
    r = dev.get_params(ParamsWhich.ACTIVE)                      # the active block stays
    assert params_bytes(r.params) == params_bytes(p) and r.source == ParamSource.UNSAVED
    stored = dev.get_params(ParamsWhich.STORED)
    assert stored.source == ParamSource.FACTORY
    with pytest.raises(DeviceError) as e:
        dev.clear_params()
    assert e.value.code == Error.FLASH_ERROR
    dev.ping()


# ----------------------------------------------------------------- bad commands

def test_bad_rate_is_bad_argument(dev):
    with pytest.raises(DeviceError) as e:
        dev.start_stream(rate_hz=123)
    assert e.value.code == Error.BAD_ARGUMENT
    assert dev.info().stream_state == StreamState.STOPPED


def test_nan_params_refused(dev):
    before = dev.get_params().params
    p = sample_params(5)
    p.gyro_b_rad_s = (0.0, math.nan, 0.0)
    with pytest.raises(DeviceError) as e:
        dev.set_params(p)
    assert e.value.code == Error.PARAM_NOT_FINITE
    assert params_bytes(dev.get_params().params) == params_bytes(before)


def raw_exchange(url: str, frame: bytes, timeout: float = 3.0) -> list:
    """Send one hand-made frame on a plain socket; return the decoded frames up to its ack."""
    host, port = url.removeprefix("socket://").split(":")
    out, buf = [], b""
    with socket.create_connection((host, int(port)), timeout=timeout) as s:
        s.sendall(b"\0" + frame)
        t_end = time.monotonic() + timeout
        while time.monotonic() < t_end:
            s.settimeout(max(0.01, t_end - time.monotonic()))
            try:
                data = s.recv(4096)
            except socket.timeout:
                break
            if not data:
                break
            buf += data
            *frames, buf = buf.split(b"\0")
            for f in frames:
                if not f:
                    continue
                fr = P.parse_frame(f)
                out.append(fr)
                if fr.type == MsgType.ACK:
                    return out
    raise AssertionError(f"no ack; got {out}")


def ack_of(frames):
    f = frames[-1]
    return P.decode_message(f.type, f.payload)


def test_unknown_command_and_bad_length_nacked(qemu):
    # unknown command type (in the command range but undefined), by a raw frame
    a = ack_of(raw_exchange(qemu.q.port_url, P.build_frame(0x7E, b"", 0x1234)))
    assert (a.request_id, a.command, a.error) == (0x1234, 0x7E, Error.UNKNOWN_COMMAND)
    # a device message type sent to the device
    a = ack_of(raw_exchange(qemu.q.port_url, P.build_frame(MsgType.ACK, bytes(8), 0x1235)))
    assert a.error == Error.UNKNOWN_COMMAND
    # ping with a 3-byte payload (4 expected)
    a = ack_of(raw_exchange(qemu.q.port_url, P.build_frame(MsgType.PING, b"\1\2\3", 0x1236)))
    assert (a.request_id, a.command, a.error, a.value) == (0x1236, MsgType.PING, Error.BAD_LENGTH, 3)
    # and the device still works
    with qemu.device() as d:
        d.ping()


def test_reboot(qemu, dev):
    info = dev.reboot(wait_s=10)
    assert info.board == BOARDS[qemu.name][0] and info.request_id == 0
    assert info.uptime_ms < 5000
    assert dev.info().param_source == ParamSource.FACTORY      # unsaved params are gone
    assert qemu.q.alive()


# ----------------------------------------------------------------- preloaded pages

@pytest.mark.parametrize("board", sorted(BOARDS))
def test_preloaded_param_page_applied_at_boot(firmware_built, board):
    lay = PS.LAYOUTS[BOARDS[board][1]]
    p = sample_params(7)
    rec = PS.params_record(p, generation=41, program_unit=lay.program_unit)
    r = start_board(board, PS.slot_image(rec, lay.slot_size))
    try:
        assert r.boot_info.param_source == ParamSource.FLASH
        assert r.boot_info.param_generation == 41
        with r.device() as d:
            info = d.info()
            assert info.param_source == ParamSource.FLASH and info.param_generation == 41
            act = d.get_params(ParamsWhich.ACTIVE)
            assert act.source == ParamSource.FLASH and act.generation == 41
            assert params_bytes(act.params) == params_bytes(p)
            st = d.get_params(ParamsWhich.STORED)
            assert params_bytes(st.params) == params_bytes(p)
            # a save goes to the other slot, fails under QEMU, and leaves the stored block
            d.set_params(sample_params(8))
            with pytest.raises(DeviceError) as e:
                d.save_params()
            assert e.value.code == Error.FLASH_ERROR
            assert params_bytes(d.get_params(ParamsWhich.STORED).params) == params_bytes(p)
    finally:
        r.q.close()


@pytest.mark.parametrize("board", sorted(BOARDS))
def test_corrupted_param_page_rejected(firmware_built, board):
    lay = PS.LAYOUTS[BOARDS[board][1]]
    rec = bytearray(PS.params_record(sample_params(9), generation=5, program_unit=lay.program_unit))
    rec[PS.HEADER_SIZE + 37] ^= 0x01                           # flip one payload bit
    with pytest.raises(PS.InvalidRecord, match="bad crc"):
        PS.parse_record(bytes(rec), program_unit=lay.program_unit)
    r = start_board(board, PS.slot_image(bytes(rec), lay.slot_size))
    try:
        assert r.boot_info.param_source == ParamSource.FACTORY
        assert r.boot_info.param_generation == 0
        with r.device() as d:
            act = d.get_params(ParamsWhich.ACTIVE)
            assert act.source == ParamSource.FACTORY
            from imubench.wire.params import identity
            assert params_bytes(act.params) == params_bytes(identity())
    finally:
        r.q.close()


def test_qemu_board_is_reaped(firmware_built):
    q = QemuBoard("f103").start()
    pid = q.proc.pid
    q.close()
    assert q.proc is None
    with pytest.raises(ProcessLookupError):
        import os
        os.kill(pid, 0)


# ----------------------------------------------------------------- paramstore.py vs the C store

CHECKER_C = r"""
/* ps_checker: the C parameter store on a RAM flash, for tests/device/test_qemu.py.
 *   ps_checker load PU SLOT_SIZE FILE        FILE = slot 0 then slot 1 (2 * SLOT_SIZE bytes)
 *   ps_checker save PU SLOT_SIZE FILE OUT    payload FILE saved on blank flash; OUT = flash
 *   ps_checker clear PU SLOT_SIZE OUT        clear on blank flash; OUT = flash
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include "param_store.h"

static uint8_t mem[2 * 8192];
static uint32_t slot_size;

static int fl_read(void *ctx, uint32_t a, void *d, size_t n)
{ (void)ctx; if (a + n > 2 * slot_size) return IB_FLASH_ERR_RANGE; memcpy(d, mem + a, n); return 0; }
static int fl_prog(void *ctx, uint32_t a, const void *d, size_t n)
{
    (void)ctx;
    if (a + n > 2 * slot_size) return IB_FLASH_ERR_RANGE;
    for (size_t i = 0; i < n; i++) {
        mem[a + i] &= ((const uint8_t *)d)[i]; /* NOR: bits only go 1 -> 0 */
    }
    return 0;
}
static int fl_erase(void *ctx, uint32_t a)
{ (void)ctx; memset(mem + a, 0xFF, slot_size); return 0; }

int main(int argc, char **argv)
{
    if (argc < 5) return 2;
    ib_flash_if_t fl = {{0, 0}, 0, (uint32_t)atoi(argv[2]), fl_erase, fl_prog, fl_read, NULL};
    slot_size = (uint32_t)atoi(argv[3]);
    fl.slot_addr[1] = slot_size; fl.slot_size = slot_size;
    memset(mem, 0xFF, sizeof mem);
    ib_ps_info_t info;
    if (!strcmp(argv[1], "load")) {
        FILE *f = fopen(argv[4], "rb"); if (!f) return 2;
        size_t got = fread(mem, 1, 2 * slot_size, f); fclose(f); (void)got;
        uint8_t pay[4096];
        ib_ps_status_t st = ib_ps_load(&fl, PV, pay, sizeof pay, &info);
        printf("status=%d slot=%d gen=%u pv=%u len=%u cleared=%d",
               (int)st, info.slot, (unsigned)info.generation, (unsigned)info.payload_version,
               (unsigned)info.payload_len, (int)info.cleared);
        for (int s = 0; s < 2; s++) {
            printf(" s%d=", s);
            for (const char *c = ib_ps_slot_state_name(info.slot_state[s]); *c; c++) putchar(*c == ' ' ? '_' : *c);
        }
        printf("\npayload=");
        if (st == IB_PS_OK) for (unsigned i = 0; i < info.payload_len; i++) printf("%02x", pay[i]);
        printf("\n");
        return 0;
    }
    ib_ps_status_t st;
    const char *out;
    if (!strcmp(argv[1], "save")) {
        if (argc < 6) return 2;
        uint8_t pay[4096];
        FILE *f = fopen(argv[4], "rb"); if (!f) return 2;
        size_t n = fread(pay, 1, sizeof pay, f); fclose(f);
        st = ib_ps_save(&fl, PV, pay, n, &info);
        out = argv[5];
    } else {
        st = ib_ps_clear(&fl, &info);
        out = argv[4];
    }
    FILE *o = fopen(out, "wb"); if (!o) return 2;
    fwrite(mem, 1, 2 * slot_size, o); fclose(o);
    printf("status=%d slot=%d gen=%u\n", (int)st, info.slot, (unsigned)info.generation);
    return st == IB_PS_OK ? 0 : 1;
}
"""


@pytest.fixture(scope="module")
def checker(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("ps_checker")
    src = d / "ps_checker.c"
    src.write_text(CHECKER_C)
    exe = d / "ps_checker"
    r = subprocess.run(["gcc", "-std=c11", "-O1", "-Wall", "-Wextra", "-Werror", f"-DPV={PS.PARAM_BLOCK_VERSION}u",
                        "-I", str(ROOT / "firmware/core"),
                        str(src), str(ROOT / "firmware/core/param_store.c"), str(ROOT / "firmware/core/crc32c.c"),
                        "-o", str(exe)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    return exe


def c_load(checker: Path, tmp: Path, slots: bytes, pu: int, slot_size: int) -> dict:
    f = tmp / "flash.bin"
    f.write_bytes(slots)
    r = subprocess.run([str(checker), "load", str(pu), str(slot_size), str(f)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    head, pay = r.stdout.splitlines()
    d = dict(kv.split("=") for kv in head.split())
    d["payload"] = bytes.fromhex(pay.removeprefix("payload="))
    return d


def c_save(checker: Path, tmp: Path, payload: bytes, pu: int, slot_size: int) -> bytes:
    (tmp / "payload.bin").write_bytes(payload)
    r = subprocess.run([str(checker), "save", str(pu), str(slot_size), str(tmp / "payload.bin"),
                        str(tmp / "out.bin")], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
    return (tmp / "out.bin").read_bytes()


def crc_forge(prefix: bytes, final_crc: int) -> bytes:
    """Four bytes that, appended to prefix, make crc32c(prefix + bytes) == final_crc."""
    poly, table = 0x82F63B78, []
    for i in range(256):
        c = i
        for _ in range(8):
            c = (c >> 1) ^ poly if c & 1 else c >> 1
        table.append(c)
    top = {t >> 24: i for i, t in enumerate(table)}
    want = final_crc ^ 0xFFFFFFFF
    ks, r = [], want
    for _ in range(4):
        k = top[r >> 24]
        ks.append(k)
        r = ((r ^ table[k]) << 8) & 0xFFFFFFFF
    out, reg = [], PS.crc32c(prefix) ^ 0xFFFFFFFF
    for k in reversed(ks):
        out.append((reg ^ k) & 0xFF)
        reg = table[k] ^ (reg >> 8)
    assert reg == want
    return bytes(out)


@pytest.mark.parametrize("pu", [1, 2, 4, 8, 32])
def test_paramstore_matches_c_save_bit_exact(checker, tmp_path, pu):
    slot_size = 1024
    payload = PS.params_payload(sample_params(pu))
    flash = c_save(checker, tmp_path, payload, pu, slot_size)
    rec = PS.params_record(sample_params(pu), generation=1, program_unit=pu)
    assert len(rec) == PS.record_size(len(payload), pu)
    assert flash[:len(rec)] == rec                              # slot 0 on blank flash, generation 1
    assert PS.parse_record(flash[:slot_size], program_unit=pu).payload == payload


@pytest.mark.parametrize("bad_crc", [0xFFFFFFFF, 0x00000000])
def test_paramstore_crc_salt_rule(checker, tmp_path, bad_crc):
    """A payload whose salt-0 CRC is 0xFFFFFFFF or 0 must be written with salt 1, by both."""
    pu, slot_size = 4, 1024
    p0 = PS.params_payload(sample_params(2))
    hdr0 = PS.HEADER.pack(PS.MAGIC, PS.FORMAT, PS.PARAM_BLOCK_VERSION, 1, len(p0), 0, 0)
    payload = p0[:-4] + crc_forge(hdr0 + p0[:-4], bad_crc)    # the last 4 bytes chosen to hit the bad CRC
    assert PS.crc32c(hdr0 + payload) == bad_crc
    rec = PS.build_record(payload, generation=1, program_unit=pu)
    assert rec[15] == 1                                        # crc_salt
    flash = c_save(checker, tmp_path, payload, pu, slot_size)
    assert flash[:len(rec)] == rec
    d = c_load(checker, tmp_path, flash, pu, slot_size)
    assert d["status"] == "0" and d["payload"] == payload


@pytest.mark.parametrize("pu,slot_size", [(2, 1024), (4, 4096)])
def test_c_store_loads_paramstore_records(checker, tmp_path, pu, slot_size):
    p_old, p_new = PS.params_payload(sample_params(10)), PS.params_payload(sample_params(11))
    s0 = PS.slot_image(PS.build_record(p_old, generation=6, program_unit=pu), slot_size)
    s1 = PS.slot_image(PS.build_record(p_new, generation=7, program_unit=pu), slot_size, fill=0x00)
    d = c_load(checker, tmp_path, s0 + s1, pu, slot_size)
    assert (d["status"], d["slot"], d["gen"]) == ("0", "1", "7") and d["payload"] == p_new
    # generation wrap: 0xFFFFFFFF is older than 1 (serial-number arithmetic)
    s0 = PS.slot_image(PS.build_record(p_old, generation=0xFFFFFFFF, program_unit=pu), slot_size)
    s1 = PS.slot_image(PS.build_record(p_new, generation=1, program_unit=pu), slot_size)
    d = c_load(checker, tmp_path, s0 + s1, pu, slot_size)
    assert (d["slot"], d["gen"]) == ("1", "1")
    # a cleared record newer than the parameters: factory defaults
    s1 = PS.slot_image(PS.cleared_record(generation=8, program_unit=pu), slot_size)
    d = c_load(checker, tmp_path, PS.slot_image(PS.build_record(p_old, generation=7, program_unit=pu),
                                                slot_size) + s1, pu, slot_size)
    assert (d["status"], d["cleared"], d["gen"]) == ("1", "1", "8")
    # a corrupted record is rejected by both, and the other slot wins
    bad = bytearray(PS.build_record(p_new, generation=9, program_unit=pu))
    bad[20] ^= 0x80
    with pytest.raises(PS.InvalidRecord, match="bad crc"):
        PS.parse_record(bytes(bad), program_unit=pu)
    d = c_load(checker, tmp_path, PS.slot_image(PS.build_record(p_old, generation=3, program_unit=pu), slot_size)
               + PS.slot_image(bytes(bad), slot_size), pu, slot_size)
    assert (d["status"], d["slot"], d["gen"], d["s1"]) == ("0", "0", "3", "bad_crc")
    assert d["payload"] == p_old


def test_paramstore_slot_parse_reasons():
    with pytest.raises(PS.InvalidRecord, match="blank"):
        PS.parse_record(bytes(1024))
    rec = bytearray(PS.params_record(sample_params(1), program_unit=4))
    crc_off = len(rec) - 4
    rec[crc_off:] = b"\xff\xff\xff\xff"
    with pytest.raises(PS.InvalidRecord, match="incomplete"):
        PS.parse_record(bytes(rec))
    with pytest.raises(ValueError):
        PS.build_record(b"x", generation=0)
    assert struct.unpack_from("<I", PS.cleared_record(), 0)[0] == PS.MAGIC
