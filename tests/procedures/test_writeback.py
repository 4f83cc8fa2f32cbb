"""The one write-back (procedures/writeback.py) without a device: an in-memory stand-in with
the Device methods the write-back uses, made to fail at each step."""
from __future__ import annotations

from dataclasses import dataclass

import pytest
from imubench.procedures.errors import SessionAborted
from imubench.procedures.presenter import Presenter
from imubench.procedures.writeback import VerifyFailed, write_and_verify, write_verified
from imubench.wire import params as PR
from imubench.wire.protocol_gen import Board


def _params(scale: float) -> object:
    p = PR.identity()
    p.accel_b_mps2 = (0.05 * scale, -0.08 * scale, 0.12 * scale)
    p.cal_id = int(100 * scale)
    return p


def _pack(p) -> bytes:
    return p.STRUCT.pack(*p.values())


def _copy(p):
    return type(p).from_values(p.values())


@dataclass
class _Readback:
    params: object
    generation: int


@dataclass
class _Stats:
    param_slot_erases: tuple = (3, 4)


@dataclass
class _Info:
    board: int = int(Board.SIM)
    param_source: int = 1


class MemoryDevice:
    """RAM and flash parameter blocks; `fail_at` names the call that raises (once)."""

    def __init__(self, fail_at: str | None = None, reboot_loses_ram: bool = False):
        self.ram = _params(1.0)
        self.flash = _params(1.0)
        self.generation = 5
        self.saves = 0
        self.fail_at = fail_at
        self.reboot_loses_ram = reboot_loses_ram
        self.last_save_unchanged = False
        self.calls: list[str] = []

    def _maybe_fail(self, name):
        self.calls.append(name)
        if self.fail_at == name:
            self.fail_at = None
            raise TimeoutError(f"no answer to {name}")

    def get_params(self, which):
        self._maybe_fail("get_params")
        return _Readback(_copy(self.ram), self.generation)

    def set_params(self, p):
        self._maybe_fail("set_params")
        self.ram = _copy(p)

    def save_params(self):
        self._maybe_fail("save_params")
        self.last_save_unchanged = _pack(self.flash) == _pack(self.ram)
        self.flash = _copy(self.ram)
        self.generation += 1
        self.saves += 1
        return self.generation

    def reboot(self, wait_s):
        self._maybe_fail("reboot")
        self.ram = _copy(self.flash if not self.reboot_loses_ram else _params(9.0))
        return _Info()

    def discard_buffered(self):
        pass

    def stats(self):
        return _Stats()

    def info(self):
        return _Info()


class Steps(Presenter):
    def __init__(self):
        self.steps: list[tuple[str, str]] = []
        self.lines: list[str] = []

    def step(self, kind, text, state):
        self.steps.append((kind, state))

    def say(self, text):
        self.lines.append(text)


def _good(_after_g: float = 1.00005):
    return lambda: [{"name": "+Z up", "after_g": _after_g, "angle_from_plan_deg": 0.1}]


def test_written_saved_rebooted_and_verified():
    dev, ui = MemoryDevice(), Steps()
    old = dev.get_params(None).params
    out = write_and_verify(dev, _params(2.0), old, _good(), verify_mg=2.0, ui=ui)
    assert out.written and out.verified and abs(out.worst_mg - 0.05) < 1e-9
    assert out.steps[:2] == ["set", "read back"] and out.steps[2].startswith("saved (generation 6)")
    assert _pack(dev.flash) == _pack(_params(2.0)) and _pack(dev.ram) == _pack(_params(2.0))
    assert ui.steps == [("write", "running"), ("write", "done"), ("verify", "running"), ("verify", "done")]


def test_a_verification_outside_its_tolerance_puts_the_previous_parameters_back():
    dev, ui = MemoryDevice(), Steps()
    old = dev.get_params(None).params
    out = write_and_verify(dev, _params(2.0), old, _good(1.005), verify_mg=2.0, ui=ui)
    assert not out.written and not out.verified and out.worst_mg == pytest.approx(5.0)
    assert _pack(dev.flash) == _pack(old) and _pack(dev.ram) == _pack(old)
    assert ui.steps[-1] == ("verify", "failed")


def test_a_verification_that_fails_restores_and_says_so():
    dev, ui = MemoryDevice(), Steps()
    old = dev.get_params(None).params

    def lost():
        raise TimeoutError("link lost")
    with pytest.raises(VerifyFailed, match="link lost; the previous parameters were restored"):
        write_and_verify(dev, _params(2.0), old, lost, verify_mg=2.0, ui=ui)
    assert _pack(dev.flash) == _pack(old) and _pack(dev.ram) == _pack(old)


@pytest.mark.parametrize("fail_at, saves", [("save_params", 0), ("reboot", 2)])
def test_a_failed_step_restores_and_saves_again_only_when_the_new_block_reached_the_flash(fail_at, saves):
    """A save that failed never wrote the flash: the restore only sets RAM; after a saved
    block the restore saves the previous block again."""
    dev = MemoryDevice()
    old = dev.get_params(None).params
    dev.fail_at = fail_at
    said = []
    with pytest.raises(TimeoutError):
        write_verified(dev, _params(2.0), previous=old, say=said.append)
    assert _pack(dev.ram) == _pack(old) and _pack(dev.flash) == _pack(old)
    assert dev.saves == saves
    assert any(s.startswith("write-back failed after:") for s in said)


def test_parameters_not_kept_across_the_reboot_are_refused_and_restored():
    dev = MemoryDevice(reboot_loses_ram=True)
    old = dev.get_params(None).params
    with pytest.raises(SessionAborted, match="after reboot the active parameters are not the ones saved"):
        write_verified(dev, _params(2.0), previous=old)
    assert _pack(dev.ram) == _pack(old) and _pack(dev.flash) == _pack(old)
