"""Flashing proven with real clients: the STM32 ROM bootloader (AN3155) under the ARM emulator
(imubench.device.arm.bootloader), Debian's stm32flash unchanged (through `imubench flash
--probe serial` and on its own) and the stm32loader package's library, a reflash that keeps the
calibration, and what goes wrong at a bench.

The reflash test calibrates a board running one image ("previous") and reflashes it with the
current build. By default the previous image is the current build with another build id
(same parameter layout). The layout-change test lays the previous layout's block in the
parameter pages and reflashes; IMUBENCH_PREV_ELF_F103 / IMUBENCH_PREV_ELF_F4 = the path of an
older commit's build/arm/<board>/imubench.elf runs that image before the reflash (see
docs/firmware.md, "A parameter-layout change")."""
from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from imubench.device.sim_gyro import NO_DRIFT as GYRO_NO_DRIFT
from imubench import units as U
from imubench.cli import main as imubench
from imubench.device.arm.bootloader import ACK, NACK, FlashFile, RomBootloader
from imubench.device.arm.targets import TARGETS as ARM
from imubench.device.flash import image_bytes, image_tag
from imubench.device.link import Device
from imubench.device.sim import VirtualBench
from imubench.procedures.session import Session, SessionConfig, SimPresenter, plan_for
from imubench.wire import params as PR
from imubench.wire import paramstore as PS
from imubench.wire.protocol_gen import ParamSource, ParamsWhich

ROOT = Path(__file__).resolve().parents[2]
PARAM_UNITS = {"f103": {62, 63}, "f4": {10, 11}}     # the parameter pages / sectors


def _pack(p) -> bytes:
    return p.STRUCT.pack(*p.values())


def _stm32flash() -> None:
    if shutil.which("stm32flash") is None:
        pytest.fail("stm32flash is not installed: `make test` installs it (SYSTEM_PKGS), or "
                    "sudo apt-get install stm32flash")


# ------------------------------------------------------------- the protocol engine
def _rom(tmp_path, name="f103"):
    t = ARM[name]
    code = FlashFile(str(tmp_path / f"{name}.code"), t.code_file_size)
    params = FlashFile(str(tmp_path / f"{name}.bin"), t.param_size)
    return RomBootloader(t, code, params, bytes(range(12)))


def _cmd(rom, code: int, *more: bytes) -> bytes:
    rom.feed(bytes([code, code ^ 0xFF]))
    for m in more:
        rom.feed(m)
    return rom.take_output()


def _addr(a: int) -> bytes:
    b = a.to_bytes(4, "big")
    return b + bytes([b[0] ^ b[1] ^ b[2] ^ b[3]])


@pytest.mark.parametrize("name,pid,version,erase", [("f103", 0x410, 0x22, 0x43), ("f4", 0x413, 0x31, 0x44)])
def test_bootloader_answers_as_the_chip(tmp_path, name, pid, version, erase):
    rom = _rom(tmp_path, name)
    rom.feed(b"\x00\x55")                                 # line noise before the sync: ignored
    assert rom.take_output() == b""
    rom.feed(b"\x7f")
    assert rom.take_output() == bytes([ACK])
    assert _cmd(rom, 0x00) == bytes([ACK, 11, version, 0x00, 0x01, 0x02, 0x11, 0x21, 0x31, erase, 0x63, 0x73,
                                     0x82, 0x92, ACK])
    assert _cmd(rom, 0x01) == bytes([ACK, version, 0, 0, ACK])
    assert _cmd(rom, 0x02) == bytes([ACK, 1, pid >> 8, pid & 0xFF, ACK])
    rom.feed(b"\x7f\x7f")                                 # a second sync byte is a bad command
    assert rom.take_output() == bytes([NACK])
    assert _cmd(rom, 0x44 if erase == 0x43 else 0x43) == bytes([NACK])   # the other erase: not offered
    t = ARM[name]
    # Write Memory: a bad checksum is NACKed and writes nothing; a good one programs
    data = bytes(range(16))
    cs = 15
    for v in data:
        cs ^= v
    assert _cmd(rom, 0x31, _addr(t.flash_base), bytes([15]) + data + bytes([cs ^ 1])) == bytes([ACK, ACK, NACK])
    assert rom.code.mem[:16] == b"\xff" * 16
    assert _cmd(rom, 0x31, _addr(t.flash_base), bytes([15]) + data + bytes([cs])) == bytes([ACK, ACK, ACK])
    assert _cmd(rom, 0x11, _addr(t.flash_base), bytes([15, 0xF0])) == bytes([ACK, ACK, ACK]) + data
    assert _cmd(rom, 0x11, _addr(0x60000000)) == bytes([ACK, NACK])     # nothing there: NACK after the address
    assert _cmd(rom, 0x11, _addr(t.uid_addr), bytes([11, 0xF4]))[3:] == bytes(range(12))
    # Go into flash leaves the bootloader
    assert _cmd(rom, 0x21, _addr(t.flash_base)) == bytes([ACK, ACK])
    assert rom.action == ("go", t.flash_base)


def _block(data: bytes) -> bytes:
    """Write Memory's N-1, the data and their XOR."""
    cs = len(data) - 1
    for v in data:
        cs ^= v
    return bytes([len(data) - 1]) + data + bytes([cs])


def _synced(tmp_path, name):
    rom = _rom(tmp_path, name)
    rom.feed(b"\x7f")
    assert rom.take_output() == bytes([ACK])
    return rom


@pytest.mark.parametrize("name", ["f103", "f4"])
def test_flash_is_contiguous_across_the_parameter_pages(tmp_path, name):
    """A read, a write and an erase across the border between code and parameter pages
    (0x0800F800 on the F103, 0x080C0000 on the F4) act on both sides, as on the chip."""
    rom = _synced(tmp_path, name)
    t = ARM[name]
    data = bytes(range(256))
    border = t.param_base
    assert _cmd(rom, 0x31, _addr(border - 128), _block(data)) == bytes([ACK, ACK, ACK])
    assert rom.code.mem[border - 128 - t.flash_base:border - t.flash_base] == data[:128]
    assert rom.params.mem[:128] == data[128:]
    assert _cmd(rom, 0x11, _addr(border - 128), bytes([255, 0])) == bytes([ACK, ACK, ACK]) + data
    # the erase of the last code page/sector and the first parameter one
    first = rom._unit_of(border)
    if name == "f103":
        assert _cmd(rom, 0x43, bytes([1, first - 1, first, 1 ^ (first - 1) ^ first])) == bytes([ACK, ACK])
    else:
        body = bytes([0, 1, 0, first - 1, 0, first])
        cs = 0
        for v in body:
            cs ^= v
        assert _cmd(rom, 0x44, body + bytes([cs])) == bytes([ACK, ACK])
    assert _cmd(rom, 0x11, _addr(border - 128), bytes([255, 0]))[3:] == b"\xff" * 256
    # the F103CB's flash goes on above its parameter pages, up to 0x0801FFFF (128 KiB)
    end = t.flash_base + t.flash_size
    assert _cmd(rom, 0x31, _addr(end - 256), _block(data)) == bytes([ACK, ACK, ACK])
    assert _cmd(rom, 0x11, _addr(end - 256), bytes([255, 0]))[3:] == data
    assert _cmd(rom, 0x11, _addr(end - 16), bytes([31, 0xE0])) == bytes([ACK, ACK, NACK])   # runs past the end
    assert _cmd(rom, 0x11, _addr(end)) == bytes([ACK, NACK])


@pytest.mark.parametrize("name,fsize,kib", [("f103", 0x1FFFF7E0, 128), ("f4", 0x1FFF7A22, 1024)])
def test_system_memory_reads_at_any_length_and_alignment(tmp_path, name, fsize, kib):
    """The flash-size register and the unique ID read the same whatever the length and the
    start of the read that covers them (stm32loader reads 256 B at 0x1FFF7A00 on an F4)."""
    rom = _synced(tmp_path, name)
    t = ARM[name]
    uid = bytes(range(12))
    for start in range(fsize - 37, fsize + 1, 3):
        for n in (2, 16, 64, 256):
            if start + n < fsize + 2:
                continue
            got = _cmd(rom, 0x11, _addr(start), bytes([n - 1, (n - 1) ^ 0xFF]))
            sysmem_end = 0x1FFFF800 if name == "f103" else 0x1FFF8000
            if start + n > sysmem_end:
                assert got == bytes([ACK, ACK, NACK])
                continue
            assert got[:3] == bytes([ACK, ACK, ACK]) and len(got) == 3 + n, (hex(start), n)
            mem = got[3:]
            assert int.from_bytes(mem[fsize - start:fsize - start + 2], "little") == kib
            if start <= t.uid_addr and t.uid_addr + 12 <= start + n:
                assert mem[t.uid_addr - start:t.uid_addr - start + 12] == uid
    got = _cmd(rom, 0x11, _addr(t.uid_addr & ~0xFF), bytes([255, 0]))
    assert got[:3] == bytes([ACK, ACK, ACK]) and len(got) == 259


@pytest.mark.parametrize("name", ["f103", "f4"])
def test_address_checks_come_right_after_the_address(tmp_path, name):
    """AN3155 3.4/3.6: an address that is not valid is NACKed right after the address and its
    checksum, before the length or the data."""
    rom = _synced(tmp_path, name)
    t = ARM[name]
    for bad in (0x00000000, 0x40000000, t.flash_base + t.flash_size, t.ram_base + t.ram_size):
        assert _cmd(rom, 0x11, _addr(bad)) == bytes([ACK, NACK]), hex(bad)
        assert _cmd(rom, 0x31, _addr(bad)) == bytes([ACK, NACK]), hex(bad)
    assert _cmd(rom, 0x31, _addr(t.ram_base)) == bytes([ACK, NACK])             # the bootloader's own RAM
    assert _cmd(rom, 0x31, _addr(t.uid_addr)) == bytes([ACK, NACK])             # system memory: read only
    assert _cmd(rom, 0x11, _addr(t.uid_addr)) == bytes([ACK, ACK])              # ... but readable
    rom.feed(bytes([11, 11 ^ 0xFF]))
    assert rom.take_output() == bytes([ACK]) + bytes(range(12))
    assert _cmd(rom, 0x31, _addr(t.flash_base + 2), _block(b"abcd")) == bytes([ACK, ACK, NACK])  # unaligned


def test_option_byte_writes_set_protection_and_reset_f103(tmp_path):
    """Write Memory to the option bytes (AN3155 3.6): programmed, then the chip resets; the
    write protection and read protection they hold take effect."""
    rom = _synced(tmp_path, "f103")
    ob = 0x1FFFF800
    assert _cmd(rom, 0x11, _addr(ob), bytes([15, 0xF0]))[3:] == bytes([0xA5, 0x5A] + [0xFF, 0x00] * 7)
    new = bytes([0xA5, 0x5A, 0xFF, 0x00, 0x12, 0xED, 0xFF, 0x00, 0xFE, 0x01, 0xFF, 0x00, 0xFF, 0x00, 0x7F, 0x80])
    assert _cmd(rom, 0x31, _addr(ob), _block(new)) == bytes([ACK, ACK, ACK])
    assert rom.action == ("reset",)
    rom.reset()
    rom.feed(b"\x7f")
    rom.take_output()
    assert _cmd(rom, 0x11, _addr(ob), bytes([15, 0xF0]))[3:] == new
    assert rom.wrp == {0, 124}                                   # WRP0 bit 0: pages 0-3, WRP3 bit 7: 124-127
    assert _cmd(rom, 0x43, bytes([0, 1, 1])) == bytes([ACK, NACK])
    assert _cmd(rom, 0x43, bytes([0, 4, 4])) == bytes([ACK, ACK])
    # RDP not 0xA5: read protection on after the reset
    assert _cmd(rom, 0x31, _addr(ob), _block(bytes([0x00, 0xFF]) + b"\xff" * 14)) == bytes([ACK, ACK, ACK])
    rom.reset()
    rom.feed(b"\x7f")
    rom.take_output()
    assert rom.rdp and _cmd(rom, 0x11) == bytes([NACK])


def test_option_byte_writes_f4(tmp_path):
    rom = _synced(tmp_path, "f4")
    ob = 0x1FFFC000
    cur = _cmd(rom, 0x11, _addr(ob), bytes([15, 0xF0]))[3:]
    assert cur[:2] == bytes([0xED, 0xAA]) and cur[8:10] == bytes([0xFF, 0x0F])
    new = bytearray(cur)
    new[8:10] = bytes([0xFF, 0x03])                              # nWRP: sectors 10 and 11 protected
    assert _cmd(rom, 0x31, _addr(ob), _block(bytes(new))) == bytes([ACK, ACK, ACK])
    assert rom.action == ("reset",)
    rom.reset()
    rom.feed(b"\x7f")
    rom.take_output()
    assert rom.wrp == {10, 11} and not rom.rdp
    assert _cmd(rom, 0x11, _addr(ob), bytes([15, 0xF0]))[3:] == bytes(new)
    t = ARM["f4"]
    assert _cmd(rom, 0x31, _addr(t.param_base), _block(b"abcd")) == bytes([ACK, ACK, NACK])   # protected


def test_erase_geometry_and_the_global_erase_f103(tmp_path):
    rom = _rom(tmp_path)
    rom.feed(b"\x7f")
    rom.take_output()
    rom.params.write(0, b"CAL!")
    # Erase pages 0 and 63 (a parameter page: the bootloader erases what it is told)
    assert _cmd(rom, 0x43, bytes([1, 0, 5, 1 ^ 0 ^ 5])) == bytes([ACK, ACK])
    assert rom.erased_units == [0, 5]
    assert _cmd(rom, 0x43, bytes([0, 127, 127])) == bytes([ACK, ACK])         # page 127: the CB's last
    assert _cmd(rom, 0x43, bytes([0, 128, 128])) == bytes([ACK, NACK])        # no page 128 on a CB
    assert _cmd(rom, 0x43, b"\xff\x00") == bytes([ACK, ACK])                   # global erase
    assert rom.params.mem[:4] == b"\xff" * 4                                   # ... wipes the calibration


def test_extended_erase_sectors_f4(tmp_path):
    rom = _rom(tmp_path, "f4")
    rom.feed(b"\x7f")
    rom.take_output()
    body = bytes([0, 1, 0, 0, 0, 4])
    cs = 0
    for v in body:
        cs ^= v
    assert _cmd(rom, 0x44, body + bytes([cs])) == bytes([ACK, ACK])
    assert [rom.units()[u] for u in rom.erased_units] == [(0x08000000, 16384), (0x08010000, 65536)]
    assert rom.units()[10] == (ARM["f4"].param_base, 131072)
    assert _cmd(rom, 0x44, b"\xff\xfe\x01") == bytes([ACK, NACK])               # bank erase: one bank here


def test_readout_and_write_protection(tmp_path):
    rom = _rom(tmp_path)
    rom.feed(b"\x7f")
    rom.take_output()
    t = ARM["f103"]
    assert _cmd(rom, 0x63, bytes([0, 32, 32])) == bytes([ACK, NACK])          # sector 32: pages 128-131, none
    assert _cmd(rom, 0x63, bytes([0, 0, 0])) == bytes([ACK, ACK])             # protect pages 0-3
    assert rom.action == ("reset",)
    rom.reset()
    rom.feed(b"\x7f")
    rom.take_output()
    assert _cmd(rom, 0x43, bytes([0, 2, 2])) == bytes([ACK, NACK])            # page 2 is protected
    assert _cmd(rom, 0x73) == bytes([ACK, ACK])
    rom.reset()
    rom.feed(b"\x7f")
    rom.take_output()
    assert _cmd(rom, 0x82) == bytes([ACK, ACK])                               # readout protection on
    rom.reset()
    rom.feed(b"\x7f")
    rom.take_output()
    assert _cmd(rom, 0x11) == bytes([NACK])
    assert _cmd(rom, 0x31) == bytes([NACK])
    assert _cmd(rom, 0x21) == bytes([NACK])
    rom.params.write(0, b"CAL!")
    assert _cmd(rom, 0x92) == bytes([ACK, ACK])                               # unprotect = mass erase
    assert rom.params.mem[:4] == b"\xff" * 4 and not rom.rdp
    assert rom.action == ("reset",)
    assert t.param_base == 0x0800F800


# ------------------------------------------------- the images stay clear of the parameters
@pytest.mark.parametrize("name", ["f103", "f4"])
def test_every_image_stays_clear_of_the_parameter_pages(name):
    """openocd's `program <elf>` erases the sectors the ELF's loadable segments touch (OpenOCD
    manual, "flash write_image erase"); st-flash `write <bin> 0x08000000` erases the pages
    [0x08000000, + length) (stlink-tools' st-flash(1)); stm32flash -S 0x08000000:<length>
    the same (run below). So no probe erases a parameter page as long as the image, rounded
    up to whole pages/sectors, ends below the first one: checked on the built image and on
    the linker script's own parameter slots."""
    t = ARM[name]
    elf = ROOT / "build" / "arm" / name / "imubench.elf"
    from elftools.elf.elffile import ELFFile
    with open(elf, "rb") as f:
        e = ELFFile(f)
        syms = {s.name: s["st_value"] for s in e.get_section_by_name(".symtab").iter_symbols()}
        end = max(seg["p_paddr"] + seg["p_filesz"] for seg in e.iter_segments()
                  if seg["p_type"] == "PT_LOAD" and seg["p_filesz"] and seg["p_paddr"] < 0x20000000)
    assert syms["__ib_param_slot0"] == t.param_base          # the emulator and the linker agree
    from imubench.device.arm.bootloader import CHIP
    a, units = t.flash_base, []
    for size in CHIP[name]["units"]:
        units.append((a, size))
        a += size
    touched = {i for i, (ua, us) in enumerate(units) if ua < end}
    assert not touched & PARAM_UNITS[name], (hex(end), sorted(touched))
    assert len(image_bytes(elf)) == end - t.flash_base


# ----------------------------------------------------------------- end to end
def _previous_image(name: str, tmp: Path) -> Path:
    """The image the board is calibrated with before the reflash (see the module docstring)."""
    env = os.environ.get(f"IMUBENCH_PREV_ELF_{name.upper()}")
    if env:
        return Path(env)
    cur = ROOT / "build" / "arm" / name / "imubench.elf"
    build = image_tag(image_bytes(cur))["build"].encode()
    prev = b"prev" + build[4:] if len(build) > 4 else b"p" * len(build)
    out = tmp / f"prev-{name}.elf"
    out.write_bytes(cur.read_bytes().replace(build + b"\0", prev + b"\0"))
    return out


def _hex(elf: Path, tmp: Path) -> Path:
    out = tmp / (elf.stem + "-" + elf.parent.name + ".hex")
    subprocess.run(["arm-none-eabi-objcopy", "-O", "ihex", str(elf), str(out)], check=True)
    return out


def _flash(name: str, port: str, image: Path, capsys) -> tuple[int, str]:
    rc = imubench(["flash", "--board", name, "--probe", "serial", "--port", port, "--image", str(image),
                   "--no-build"])
    cap = capsys.readouterr()
    return rc, cap.out + cap.err


def _erased(log: str) -> set[int]:
    out = set()
    for line in log.splitlines():
        if "bootloader: erased" in line:
            out |= {int(n) for n in re.findall(r"(?:page|sector) (\d+) \(", line)}
    return out


@pytest.mark.parametrize("name", ["f103", "f4"])
def test_stm32flash_writes_starts_and_a_reflash_keeps_the_calibration(name, tmp_path, capsys):
    """stm32flash writes, verifies and starts the previous image; the board, BOOT0 low, passes
    a calibration session (six faces, gyro bias) and saves it; BOOT0 high again, stm32flash writes the current
    build (only the image's pages/sectors erased, the parameter file untouched); BOOT0 low,
    the new image boots with the same parameters from flash and calibrated output."""
    _stm32flash()
    cur_elf = ROOT / "build" / "arm" / name / "imubench.elf"
    prev_elf = _previous_image(name, tmp_path)
    flash = tmp_path / "flash.bin"
    elfs = [str(prev_elf), str(cur_elf)]

    def boot0_bench():
        return VirtualBench(speed=0, seed=41, target=name, flash=flash, pty=True, tcp=False, boot0=True, elf=elfs)

    with boot0_bench() as vb:
        rc, out = _flash(name, vb.pty, _hex(prev_elf, tmp_path), capsys)
        assert rc == 0, out + vb.log
        assert "Device ID    : 0x%04x" % (0x410 if name == "f103" else 0x413) in out
        assert "Wrote and verified address" in out and "Starting execution at address 0x08000000... done." in out
        assert f"Go 0x08000000: starting {prev_elf}" in vb.log
        assert re.search(r"image: build \S+, \d+ bytes, sha256 [0-9a-f]{64}", out)
        assert f"device: board STM32F{'103' if name == 'f103' else '4'}" in out      # info after boot
        assert not _erased(vb.log) & PARAM_UNITS[name]

    with VirtualBench(speed=0, seed=41, truth="random", target=name, flash=flash, elf=elfs) as vb:
        assert f'"elf": "{prev_elf}"' in Path(vb.log_path).read_text() or vb.info["elf"]
        vb.set_truth(accel={"rw_k": 0.0}, gyro=[GYRO_NO_DRIFT] * 3)
        # the six faces and the gyro bias from the rests: a whole session (capture, fit, write
        # back, save by the image's flash driver) at a fraction of the 26-attitude multi-position
        # session with turntable, which tests/device/test_arm_images.py runs on both images
        cfg = SessionConfig(method="six", gyro="bias", rate_hz=100, rest_s=0.5, settle_s=0.1, hold_s=0.25)
        with Device.open(vb.port_url, timeout=10.0) as dev:
            prev_tag = image_tag(image_bytes(prev_elf))    # None: an image from before the board tag
            assert prev_tag is None or dev.info().fw_build == prev_tag["build"]
            s = Session(dev, tmp_path / "s", cfg, SimPresenter(vb, rate_dps=1000, quiet=True))
            result = s.run(plan_for("six"))
            assert result["passed"], result
            wb = s.write_back(s.accel_fit, s.gyro_fit, cal_id=7)
            stored = _pack(dev.get_params(ParamsWhich.STORED).params)
    params_before = flash.read_bytes()

    with boot0_bench() as vb:
        rc, out = _flash(name, vb.pty, _hex(cur_elf, tmp_path), capsys)
        assert rc == 0, out + vb.log
        assert f"Go 0x08000000: starting {cur_elf}" in vb.log
        erased = _erased(vb.log)
        assert erased and not erased & PARAM_UNITS[name], erased
        assert "parameters: FLASH" in out
    assert flash.read_bytes() == params_before                   # not one byte of the slots changed

    with VirtualBench(speed=0, seed=41, truth="random", target=name, flash=flash, elf=elfs) as vb:
        vb.set_truth(accel={"rw_k": 0.0}, gyro=[GYRO_NO_DRIFT] * 3)
        with Device.open(vb.port_url, timeout=10.0) as dev:
            info = dev.info()
            assert info.fw_build == image_tag(image_bytes(cur_elf))["build"]
            assert info.param_source == ParamSource.FLASH and info.param_generation == wb["generation"]
            assert _pack(dev.get_params(ParamsWhich.STORED).params) == stored
            dev.start_stream(100, calibrated=True)
            block = dev.read(duration_s=0.5)
            dev.stop_stream()
    g = np.linalg.norm(block.accel_mps2.mean(axis=0)) / U.G0_MPS2
    assert abs(g - 1.0) < 2e-3, g                                 # the device's own calibrated output


@pytest.mark.parametrize("name", ["f103", "f4"])
def test_a_reflash_keeps_a_block_the_previous_layout_stored(name, tmp_path, capsys):
    """The parameter layout moved (2 -> 3, issue 23) and the board's parameter pages hold the
    block the previous firmware stored (layout 2, byte for byte as its ib_ps_save wrote it:
    paramstore.params_record(layout=2), checked against the C store in tests/device/test_qemu.py).
    stm32flash writes the current image over the previous one; the parameter pages are not
    touched, and the new image boots using that block (migrated: c2 = c3 = 0, span −40..85 °C,
    its G kept), not factory defaults.
    Set IMUBENCH_PREV_ELF_F103 / _F4 to images built from a commit before the layout change to
    run the previous image itself (docs/firmware.md); by default it is the current build
    relabelled, since only the flash contents matter to what the new image reads."""
    _stm32flash()
    cur_elf = ROOT / "build" / "arm" / name / "imubench.elf"
    elfs = [str(_previous_image(name, tmp_path)), str(cur_elf)]
    p = PR.identity()
    p.accel_m = (1.004, 0.001, 0.0, -0.002, 0.997, 0.0, 0.003, 0.0, 1.01)
    p.accel_b_mps2 = (0.05, -0.08, 0.12)
    p.gyro_b_rad_s = (0.004, -0.002, 0.001)
    p.cal_id = 4321
    p.gyro_g_rad_s_per_mps2 = (float(np.float32(5e-5)),) + (0.0,) * 8
    lay = PS.LAYOUTS[name]
    rec = PS.params_record(p, generation=17, program_unit=lay.program_unit, layout=2)
    flash = tmp_path / "flash.bin"
    img = bytearray(b"\xff" * ARM[name].param_size)         # both parameter pages / sectors
    img[:len(rec)] = rec
    flash.write_bytes(bytes(img))
    with VirtualBench(speed=0, seed=43, target=name, flash=flash, pty=True, tcp=False, boot0=True, elf=elfs) as vb:
        rc, out = _flash(name, vb.pty, _hex(cur_elf, tmp_path), capsys)
        assert rc == 0, out + vb.log
        assert f"Go 0x08000000: starting {cur_elf}" in vb.log
        assert not _erased(vb.log) & PARAM_UNITS[name]
        assert "parameters: FLASH" in out
    assert flash.read_bytes() == bytes(img)                       # the slots as the old firmware left them
    with VirtualBench(speed=0, seed=43, target=name, flash=flash, elf=elfs) as vb:
        with Device.open(vb.port_url, timeout=10.0) as dev:
            info = dev.info()
            assert info.fw_build == image_tag(image_bytes(cur_elf))["build"]
            assert info.param_source == ParamSource.FLASH and info.param_generation == 17
            got = dev.get_params(ParamsWhich.STORED).params
            assert _pack(got) == _pack(p) and (got.gyro_t_min_c, got.gyro_t_max_c) == (-40, 85)
            assert not any(got.accel_bias_tc2_mps2_per_c2 + got.gyro_bias_tc3_rad_s_per_c3)


# ------------------------------------------- two clients, across the parameter pages
def _boot0(name, tmp_path, seed=5):
    return VirtualBench(speed=0, seed=seed, target=name, flash=tmp_path / "flash.bin", pty=True, tcp=False,
                        boot0=True)


def _stores(tmp_path, name, addr: int, n: int) -> bytes:
    """[addr, addr+n) of the board's flash, from its two files (code and parameter pages)."""
    t = ARM[name]
    code = Path(str(tmp_path / "flash.bin") + ".code").read_bytes()
    params = (tmp_path / "flash.bin").read_bytes()
    whole = code[:t.param_base - t.flash_base] + params + code[t.param_base - t.flash_base:]
    assert len(whole) == t.flash_size
    return whole[addr - t.flash_base:addr - t.flash_base + n]


def _sf(*args) -> subprocess.CompletedProcess:
    return subprocess.run(["stm32flash", "-m", "8n1", *args], capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("name", ["f103", "f4"])
def test_stm32flash_across_the_parameter_pages(name, tmp_path):
    """Debian's stm32flash, unchanged: writes, verifies, reads back and erases 8 KiB across the
    border between code and parameter pages; on the F103 it reads the whole flash (-r, its own
    help's example) and computes its CRC (-C) up to 0x08020000, the CB's 128 KiB. A .bin
    written without -S erases only the file's pages (docs/firmware.md: not a mass erase)."""
    _stm32flash()
    t = ARM[name]
    start, n = t.param_base - 4096, 8192
    data = np.random.default_rng(3).integers(0, 256, n, dtype=np.uint8).tobytes()
    src = tmp_path / "across.bin"
    src.write_bytes(data)
    back = tmp_path / "back.bin"
    with _boot0(name, tmp_path) as vb:
        r = _sf("-w", str(src), "-v", "-S", f"0x{start:08X}:{n}", vb.pty)
        assert r.returncode == 0, r.stdout + r.stderr + vb.log
        assert "Wrote and verified address" in r.stdout
        assert _stores(tmp_path, name, start, n) == data
        assert set(_erased(vb.log)) & PARAM_UNITS[name]         # the erase took the parameter page too
        r = _sf("-r", str(back), "-S", f"0x{start:08X}:{n}", vb.pty)
        assert r.returncode == 0 and back.read_bytes() == data, r.stdout + r.stderr
        units = [(a, s) for a, s in _units(name) if a < start + n and start < a + s]   # erase-only: whole units
        e0, e1 = units[0][0], units[-1][0] + units[-1][1]
        log_at = len(vb.log)
        r = _sf("-o", "-S", f"0x{e0:08X}:{e1 - e0}", vb.pty)
        assert r.returncode == 0, r.stdout + r.stderr
        assert _erased(vb.log[log_at:]) == {i for i, u in enumerate(_units(name)) if u in units}
        assert _stores(tmp_path, name, e0, e1 - e0) == b"\xff" * (e1 - e0)
        if name == "f103":
            whole = tmp_path / "whole.bin"
            r = _sf("-r", str(whole), vb.pty)
            assert r.returncode == 0, r.stdout + r.stderr
            assert whole.read_bytes() == _stores(tmp_path, name, t.flash_base, t.flash_size)
            assert len(whole.read_bytes()) == 128 * 1024
            r = _sf("-C", vb.pty)
            assert r.returncode == 0, r.stdout + r.stderr
            crc = _stm32_crc(_stores(tmp_path, name, t.flash_base, t.flash_size))
            assert f"CRC(0x08000000-0x08020000) = 0x{crc:08x}" in r.stdout, r.stdout
            # a .bin without -S: stm32flash 0.7 erases the pages the file covers, not the flash
            params = (tmp_path / "flash.bin").read_bytes()
            small = tmp_path / "small.bin"
            small.write_bytes(bytes(range(256)) * 12)           # 3 KiB: pages 0-2
            log_at = len(vb.log)
            r = _sf("-w", str(small), vb.pty)
            assert r.returncode == 0, r.stdout + r.stderr
            assert _erased(vb.log[log_at:]) == {0, 1, 2}
            assert "mass erase" not in vb.log[log_at:]
            assert (tmp_path / "flash.bin").read_bytes() == params


@pytest.mark.parametrize("name", ["f103", "f4"])
def test_stm32loader_library_across_the_parameter_pages(name, tmp_path):
    """The stm32loader package's library (Stm32Bootloader over its SerialConnection on the
    emulator's pty). Its command line starts by resetting the chip into the bootloader with
    RTS/DTR, which a pseudo-terminal does not carry (pyserial's modem-line ioctls fail on a
    pty), so the test sends the 0x7F synchronisation itself and then drives the library as its
    main does: Get, Get Version, Get ID, the flash size and UID it reads from system memory,
    page/sector erase, write, read and verify across the parameter pages, global erase."""
    from stm32loader.bootloader import Stm32Bootloader
    from stm32loader.uart import SerialConnection
    t = ARM[name]
    family = "F1" if name == "f103" else "F4"
    start, n = t.param_base - 4096, 8192
    data = np.random.default_rng(4).integers(0, 256, n, dtype=np.uint8).tobytes()
    with _boot0(name, tmp_path, seed=6) as vb:
        conn = SerialConnection(vb.pty, 115200, "N")      # a pty refuses PARENB (8E1), as with stm32flash -m 8n1
        conn.connect()
        try:
            bl = Stm32Bootloader(conn, device_family=family, verbosity=0, show_progress=False)
            bl.write(bl.Command.SYNCHRONIZE)
            assert conn.read()[0] == bl.Reply.ACK
            assert bl.get() == (0x22 if name == "f103" else 0x31)
            assert bl.get_version() == (0x22 if name == "f103" else 0x31)
            assert bl.get_id() == (0x410 if name == "f103" else 0x413)
            if name == "f103":
                size_kib, uid_read = bl.get_flash_size(), bytes(bl.get_uid())
            else:
                size_kib, uid_read = bl.get_flash_size_and_uid()
                uid_read = bytes(uid_read)
            assert size_kib == t.flash_kib
            assert len(uid_read) == 12 and uid_read == bytes(bl.read_memory(t.uid_addr, 12))
            assert uid_read == bytes.fromhex(vb.info["uid"])       # the board's own ID
            units = [i for i, (a, s) in enumerate(_units(name)) if a < start + n and start < a + s]
            assert set(units) & PARAM_UNITS[name]
            if name == "f103":
                bl.erase_memory(units)
            else:
                bl.extended_erase_memory(units)
            bl.write_memory_data(start, data)
            got = bytes(bl.read_memory_data(start, n))
            bl.verify_data(got, data)
            assert got == data and _stores(tmp_path, name, start, n) == data
            bl.erase_memory() if name == "f103" else bl.extended_erase_memory()   # global / mass erase
            assert _stores(tmp_path, name, t.flash_base, t.flash_size) == b"\xff" * t.flash_size
        finally:
            conn.disconnect()


def _stm32_crc(data: bytes) -> int:
    """The STM32 CRC unit's CRC-32 (polynomial 0x04C11DB7, initial 0xFFFFFFFF, 32-bit words
    fed MSB first, RM0008 20.3; stm32flash computes the same): CRC-32/MPEG-2 over each
    little-endian word's bytes reversed."""
    table = []
    for i in range(256):
        c = i << 24
        for _ in range(8):
            c = ((c << 1) ^ 0x04C11DB7) if c & 0x80000000 else c << 1
        table.append(c & 0xFFFFFFFF)
    crc = 0xFFFFFFFF
    for i in range(0, len(data), 4):
        for b in data[i:i + 4][::-1]:
            crc = ((crc << 8) & 0xFFFFFFFF) ^ table[(crc >> 24) ^ b]
    return crc


def _units(name):
    from imubench.device.arm.bootloader import CHIP
    a, out = ARM[name].flash_base, []
    for size in CHIP[name]["units"]:
        out.append((a, size))
        a += size
    return out

# ------------------------------------------------------------- what goes wrong at a bench
def test_bench_faults_power_cut_wrong_chip_not_a_bootloader(tmp_path, capsys):
    """Power cut half way through the write: stm32flash fails, the board is not bricked (the
    bootloader is in ROM), the next imubench flash writes it again and it boots. The link
    dropped mid-write: the bootloader waits for the rest of the frame, the next flash asks for
    a reset, after which it writes the board again. An F103
    image for an F4 (board tag) and an F103 flash of an F4 chip (product ID) are refused
    before anything is erased; a port with a running image is not a bootloader."""
    _stm32flash()
    flash = tmp_path / "f.bin"
    hex103 = ROOT / "build" / "arm" / "f103" / "imubench.hex"
    hex4 = ROOT / "build" / "arm" / "f4" / "imubench.hex"
    # the wrong image for the board: refused from its own tag, no port touched
    rc, out = _flash("f103", "/dev/null", hex4, capsys)
    assert rc == 2 and "image for the stm32f4, not the stm32f103" in out and "nothing written" in out
    with VirtualBench(speed=0, seed=2, target="f103", flash=flash, pty=True, tcp=False, boot0=True) as vb:
        n_pages = -(-len(image_bytes(hex103)) // 1024)
        vb.power_cut(after_flash_ops=n_pages + 10)           # the 10th Write Memory block
        rc, out = _flash("f103", vb.pty, hex103, capsys)
        assert rc == 1, out
        err = out.strip().splitlines()[-1]
        assert err.startswith("imubench flash: error: stm32flash failed"), out
        assert "power cut during the write" in vb.log
        assert vb.status()["power_cuts"] == 1
        rc, out = _flash("f103", vb.pty, hex103, capsys)    # the next flash writes it again
        assert rc == 0, out + vb.log
        assert "device: board STM32F103" in out
        # the link dropped half way through a Write Memory frame (the adapter pulled mid-block):
        # written by hand so that the cut falls inside a frame every time (killing stm32flash
        # lands between two frames as often as inside one, and then nothing is left half done)
        import time
        import serial
        waiting = vb.log.count("waiting for 0x7F")
        vb.power_cut()                                      # a reset, BOOT0 still high: the bootloader
        deadline = time.monotonic() + 10
        while vb.log.count("waiting for 0x7F") == waiting and time.monotonic() < deadline:
            time.sleep(0.05)
        log_at_reset = len(vb.log)
        with serial.Serial(vb.pty, timeout=5) as port:
            def said(req: bytes) -> bytes:
                port.write(req)
                return port.read(1)
            assert said(b"\x7f") == bytes([ACK])
            assert said(b"\x31\xce") == bytes([ACK])                   # Write Memory
            addr = (0x08000000).to_bytes(4, "big")
            assert said(addr + bytes([addr[0] ^ addr[1] ^ addr[2] ^ addr[3]])) == bytes([ACK])
            port.write(bytes([255]) + bytes(100))                        # 256 bytes announced, 100 sent
            port.flush()
        assert "Go 0x08000000" not in vb.log[log_at_reset:]                     # it never finished
        # the bootloader waits for the rest of the Write Memory frame (AN3155 has no timeout), as
        # the chip does: the next flash says to reset it; after a reset (BOOT0 still high) it works
        rc, out = _flash("f103", vb.pty, hex103, capsys)
        assert rc == 1 and "does not answer as an STM32 bootloader" in out and "reset" in out, out
        vb.power_cut()
        rc, out = _flash("f103", vb.pty, hex103, capsys)
        assert rc == 0, out + vb.log
        assert "device: board STM32F103" in out
    code = Path(str(flash) + ".code")
    with VirtualBench(speed=0, seed=2, target="f4", flash=tmp_path / "g.bin", pty=True, tcp=False,
                      boot0=True) as vb:
        before = Path(str(tmp_path / "g.bin") + ".code").read_bytes()
        rc, out = _flash("f103", vb.pty, hex103, capsys)
        assert rc == 2 and "reports product ID 0x413 (f4), not the f103's 0x410: nothing erased" in out, out
        assert "bootloader: erased" not in vb.log
        assert Path(str(tmp_path / "g.bin") + ".code").read_bytes() == before
    assert code.exists()
    with VirtualBench(speed=0, seed=2, target="f103", flash=flash, pty=True, tcp=False) as vb:   # BOOT0 low
        rc, out = _flash("f103", vb.pty, hex103, capsys)
        assert rc == 1 and "does not answer as an STM32 bootloader" in out.strip().splitlines()[-1], out
