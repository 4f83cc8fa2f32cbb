"""`imubench flash` (imubench.device.flash.main_flash) against stand-in flashing tools.

Each stand-in is a shell script on a private PATH that records its argv in a log and exits
0, or 1 with an error message when $FAKE_FAIL names it. The st-flash stand-in answers
`read FILE ...` by copying $FAKE_READ_SRC to FILE (the flash contents the verify sees).
"""
from __future__ import annotations

import os
from pathlib import Path

import pytest
from imubench.cli import main as imubench

ROOT = Path(__file__).resolve().parents[2]

STANDIN = """#!/bin/sh
name=$(/usr/bin/basename "$0")
{
  echo "=== $name"
  for a in "$@"; do echo "$a"; done
} >> "$FAKE_LOG"
if [ "$name" = "st-flash" ] && [ "$1" = "read" ] && [ -n "$FAKE_READ_SRC" ]; then
  /bin/cp "$FAKE_READ_SRC" "$2"
fi
echo "$name: stand-in ran"
if [ "$name" = "stm32flash" ] && [ -n "$FAKE_PID" ]; then
  echo "Device ID    : $FAKE_PID (stand-in)"
fi
if [ -n "$FAKE_VERIFY_FAIL" ] && [ "$name" = "stm32flash" ] && [ "$1" = "-S" ]; then
  echo "Failed to verify at address 0x08000100, expected 0x12 and found 0xff" >&2
  exit 1
fi
if [ "$FAKE_FAIL" = "$name" ]; then
  echo "Error: $name stand-in: no target connected" >&2
  exit 1
fi
exit 0
"""

TOOLS = ("openocd", "st-flash", "stm32flash")


@pytest.fixture
def env(tmp_path, monkeypatch):
    """A PATH with only the chosen stand-ins; returns (install, calls, images)."""
    bindir = tmp_path / "bin"
    bindir.mkdir()
    log = tmp_path / "calls.log"
    log.write_text("")
    monkeypatch.setenv("PATH", str(bindir))
    monkeypatch.setenv("FAKE_LOG", str(log))
    monkeypatch.delenv("FAKE_FAIL", raising=False)
    monkeypatch.delenv("FAKE_READ_SRC", raising=False)
    monkeypatch.setenv("FAKE_PID", "0x0410")
    # no board behind a stand-in: the identity read after the start is stubbed (the real
    # one is tested against the emulated bootloader, tests/device/test_rom_bootloader.py)
    import imubench.cli.flash as cli_flash
    monkeypatch.setattr(cli_flash, "_print_identity", lambda port: print(f"identity of the board on {port}"))
    monkeypatch.delenv("FAKE_VERIFY_FAIL", raising=False)
    img = tmp_path / "img"
    img.mkdir()
    images = {ext: img / f"imubench.{ext}" for ext in ("elf", "bin", "hex")}
    images["elf"].write_bytes(b"\x7fELF fake image")
    images["bin"].write_bytes(bytes(range(256)) * 37 + b"tail")
    images["hex"].write_text(":00000001FF\n")
    images["port"] = tmp_path / "ttyUSB7"          # stands for the adapter's device node
    images["port"].write_text("")

    def install(*tools):
        for t in tools:
            p = bindir / t
            p.write_text(STANDIN)
            p.chmod(0o755)

    def calls():
        out, cur = [], None
        for line in log.read_text().splitlines():
            if line.startswith("=== "):
                cur = [line[4:]]
                out.append(cur)
            else:
                cur.append(line)
        return out

    return install, calls, images


def test_openocd_f103_command_line(env, capsys):
    install, calls, img = env
    install(*TOOLS)
    assert imubench(["flash", "--board", "f103", "--image", str(img["elf"])]) == 0   # openocd is first
    assert calls() == [["openocd", "-f", "interface/stlink.cfg", "-f", "target/stm32f1x.cfg",
                        "-c", f"program {img['elf']} verify reset exit"]]
    out = capsys.readouterr().out
    assert "openocd: stand-in ran" in out and "done" in out


def test_openocd_f4_uses_the_f4_target(env):
    install, calls, img = env
    install("openocd")
    assert imubench(["flash", "--board", "f4", "--probe", "openocd", "--image", str(img["elf"])]) == 0
    assert calls() == [["openocd", "-f", "interface/stlink.cfg", "-f", "target/stm32f4x.cfg",
                        "-c", f"program {img['elf']} verify reset exit"]]


def test_stlink_writes_then_verifies_by_reading_back(env, monkeypatch, capsys):
    install, calls, img = env
    install("st-flash", "stm32flash")                                       # no openocd: st-flash next
    monkeypatch.setenv("FAKE_READ_SRC", str(img["bin"]))
    assert imubench(["flash", "--board", "f103", "--image", str(img["bin"])]) == 0
    c = calls()
    size = img["bin"].stat().st_size
    assert c[0] == ["st-flash", "--reset", "write", str(img["bin"]), "0x08000000"]
    assert c[1][:2] == ["st-flash", "read"] and c[1][3:] == ["0x08000000", f"0x{size:x}"]
    assert c[2] == ["st-flash", "reset"]
    assert len(c) == 3
    assert f"verified: {size} bytes" in capsys.readouterr().out


def test_stlink_verify_mismatch_fails(env, monkeypatch, tmp_path, capsys):
    install, calls, img = env
    install("st-flash")
    bad = bytearray(img["bin"].read_bytes())
    bad[0x123] ^= 0xFF
    (tmp_path / "bad.bin").write_bytes(bytes(bad))
    monkeypatch.setenv("FAKE_READ_SRC", str(tmp_path / "bad.bin"))
    assert imubench(["flash", "--board", "f4", "--probe", "stlink", "--image", str(img["bin"])]) == 1
    err = capsys.readouterr().err
    assert "verify failed" in err and "0x123" in err and "0x08000123" in err
    assert [c[1] for c in calls()] == ["--reset", "read"]                   # no reset after a bad verify


def test_stlink_needs_a_bin_image(env, capsys):
    install, calls, img = env
    install("st-flash")
    assert imubench(["flash", "--board", "f103", "--probe", "stlink", "--image", str(img["elf"])]) == 2
    assert ".bin" in capsys.readouterr().err
    assert calls() == []


def test_serial_bootloader_command_line(env):
    install, calls, img = env
    install("stm32flash")
    assert imubench(["flash", "--board", "f103", "--port", str(img["port"]), "--image", str(img["hex"])]) == 0
    assert calls() == [["stm32flash", str(img["port"])],
                       ["stm32flash", "-S", "0x08000000:0", "-w", str(img["hex"]), "-v", "-g", "0x08000000",
                        str(img["port"])]]


def test_serial_port_that_does_not_exist(env, capsys):
    install, calls, img = env
    install("stm32flash")
    assert imubench(["flash", "--board", "f103", "--port", "/dev/ttyUSB9-none", "--image", str(img["hex"])]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "/dev/ttyUSB9-none: no such serial port" in err[0]
    assert calls() == []


def test_serial_verify_mismatch_is_one_line(env, monkeypatch, capsys):
    install, calls, img = env
    install("stm32flash")
    monkeypatch.setenv("FAKE_VERIFY_FAIL", "1")
    assert imubench(["flash", "--board", "f103", "--port", str(img["port"]), "--image", str(img["hex"])]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["imubench flash: error: verify failed: Failed to verify at address 0x08000100, "
                   "expected 0x12 and found 0xff; see docs/firmware.md, Flashing"]


def test_serial_refuses_another_chip_before_erasing(env, monkeypatch, capsys):
    install, calls, img = env
    install("stm32flash")
    monkeypatch.setenv("FAKE_PID", "0x0413")
    assert imubench(["flash", "--board", "f103", "--port", str(img["port"]), "--image", str(img["hex"])]) == 2
    assert "product ID 0x413 (f4), not the f103's 0x410: nothing erased" in capsys.readouterr().err
    assert calls() == [["stm32flash", str(img["port"])]]                      # the write never ran


def test_serial_needs_a_port(env, capsys):
    install, calls, img = env
    install("stm32flash")
    assert imubench(["flash", "--board", "f4", "--probe", "serial", "--image", str(img["hex"])]) == 2
    assert "--port" in capsys.readouterr().err
    assert calls() == []


def test_no_tool_found_says_what_to_install(env, capsys):
    _install, calls, img = env
    assert imubench(["flash", "--board", "f103", "--image", str(img["elf"])]) == 1   # the environment lacks it
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and err.startswith("imubench flash: error: ")
    for tool, pkg in (("openocd", "openocd"), ("st-flash", "stlink-tools"), ("stm32flash", "stm32flash")):
        assert tool in err and f"apt-get install {pkg}" in err
    assert calls() == []


def test_requested_probe_missing(env, capsys):
    install, _calls, img = env
    install("openocd")
    assert imubench(["flash", "--board", "f103", "--probe", "stlink", "--image", str(img["bin"])]) == 1
    err = capsys.readouterr().err
    assert "st-flash" in err and "apt-get install stlink-tools" in err


@pytest.mark.parametrize("tool,args", [
    ("openocd", ["--probe", "openocd"]),
    ("st-flash", ["--probe", "stlink"]),
    ("stm32flash", ["--probe", "serial", "--port", "PORT"]),
])
def test_tool_failure_exits_non_zero_with_its_output(env, monkeypatch, capsys, tool, args):
    install, calls, img = env
    install(*TOOLS)
    monkeypatch.setenv("FAKE_FAIL", tool)
    ext = {"openocd": "elf", "st-flash": "bin", "stm32flash": "hex"}[tool]
    args = [str(img["port"]) if x == "PORT" else x for x in args]
    assert imubench(["flash", "--board", "f103", "--image", str(img[ext]), *args]) == 1
    cap = capsys.readouterr()
    assert f"{tool} failed (exit 1)" in cap.err or tool == "stm32flash"
    assert f"Error: {tool} stand-in: no target connected" in cap.out + cap.err
    assert len(calls()) == 1                                                # stops at the first failure
    if tool == "stm32flash":
        assert "does not answer as an STM32 bootloader" in cap.err


def test_dry_run_runs_nothing(env, capsys):
    install, calls, img = env
    install(*TOOLS)
    assert imubench(["flash", "--board", "f4", "--dry-run"]) == 0
    out = capsys.readouterr().out
    elf = ROOT / "build" / "arm" / "f4" / "imubench.elf"
    assert f'openocd -f interface/stlink.cfg -f target/stm32f4x.cfg -c \'program {elf} verify reset exit\'' in out
    assert calls() == []
    assert imubench(["flash", "--board", "f103", "--probe", "stlink", "--dry-run", "--image", str(img["bin"])]) == 0
    out = capsys.readouterr().out
    assert f"st-flash --reset write {img['bin']} 0x08000000" in out and "st-flash reset" in out
    assert calls() == []


def test_dry_run_with_a_probe_needs_no_tool(env, capsys):
    _install, calls, img = env
    assert imubench(["flash", "--board", "f103", "--probe", "serial", "--port", "/dev/ttyUSB0", "--dry-run",
                       "--image", str(img["hex"])]) == 0
    out = capsys.readouterr().out
    assert f"stm32flash -S 0x08000000:0 -w {img['hex']} -v -g 0x08000000 /dev/ttyUSB0" in out
    assert "stm32flash /dev/ttyUSB0" in out


def test_missing_image(env, tmp_path, capsys):
    install, calls, _img = env
    install("openocd")
    assert imubench(["flash", "--board", "f103", "--image", str(tmp_path / "nope.elf")]) == 2   # checked as an argument
    assert "nope.elf: no such file" in capsys.readouterr().err
    assert calls() == []


def test_default_image_is_the_built_one(env, capsys):
    install, calls, _img = env
    install("openocd")
    assert imubench(["flash", "--board", "f103", "--dry-run"]) == 0
    assert str(ROOT / "build" / "arm" / "f103" / "imubench.elf") in capsys.readouterr().out
    assert os.environ["PATH"].endswith("bin")
