"""The emulated Cortex-M core's own exception entry and return (imubench.device.arm.core),
on a few hand-assembled instructions rather than an image: the cases that an image hits only
when an interrupt lands on one particular instruction."""
from __future__ import annotations

from types import SimpleNamespace

import pytest
from unicorn import UC_HOOK_BLOCK, UC_HOOK_INTR
from unicorn import arm_const as A

from imubench.device.arm.core import EXCP_EXCEPTION_EXIT, Cpu

FLASH, RAM = 0x08000000, 0x20000000
VTOR = FLASH
SYSTICK = 15
HANDLER = FLASH + 0x500
PAGE_END = FLASH + 0x400      # QEMU's Cortex-M translation blocks end at 1 KB pages


def _hw(*halfwords: int) -> bytes:
    return b"".join(h.to_bytes(2, "little") for h in halfwords)


def _core(cpu_model: str):
    cpu = Cpu(machine=None, target=SimpleNamespace(cpu=cpu_model), image=None, lib=None)
    uc = cpu.uc
    uc.mem_map(FLASH, 0x1000)
    uc.mem_map(RAM, 0x1000)
    uc.mem_write(VTOR + 4 * SYSTICK, (HANDLER | 1).to_bytes(4, "little"))
    # thread code: an IT block whose first conditional instruction starts the next page
    uc.mem_write(PAGE_END - 8, _hw(
        0x2000,          # movs r0, #0
        0x2801,          # cmp r0, #1         (Z clear: eq false, ne true)
        0xBF00,          # nop
        0xBF0C,          # ite eq
        0x2101,          # movs r1, #1        (eq: must not run)   <- page boundary
        0x2202,          # movs r2, #2        (ne: must run)
        0xE7FE))         # b .
    # the handler: its first instruction must run unconditionally
    uc.mem_write(HANDLER, _hw(0x2355, 0x4770))   # movs r3, #0x55 ; bx lr
    uc.reg_write(A.UC_ARM_REG_SP, RAM + 0x800)
    uc.reg_write(A.UC_ARM_REG_MSP, RAM + 0x800)
    uc.reg_write(A.UC_ARM_REG_LR, 0xFFFFFFFF)

    def on_intr(uc, intno, _):
        assert intno == EXCP_EXCEPTION_EXIT
        cpu.exc_exit = True
        uc.emu_stop()
    uc.hook_add(UC_HOOK_INTR, on_intr)
    return cpu


@pytest.mark.parametrize("cpu_model", ["cortex-m3", "cortex-m4"])
def test_an_interrupt_inside_an_it_block_neither_leaks_nor_loses_its_condition(cpu_model):
    cpu = _core(cpu_model)
    uc = cpu.uc
    stopped = []

    def stop_at_the_page(uc, addr, size, _):
        if addr == PAGE_END and not stopped:   # where the emulator's instruction limit stops it
            stopped.append(addr)
            uc.emu_stop()
    hook = uc.hook_add(UC_HOOK_BLOCK, stop_at_the_page)
    uc.emu_start((PAGE_END - 8) | 1, PAGE_END + 6)
    assert stopped and cpu.pc() == PAGE_END
    assert uc.reg_read(A.UC_ARM_REG_XPSR) & 0x0600FC00, "the core should be inside the IT block here"
    uc.hook_del(hook)

    cpu.enter_exception(SYSTICK, VTOR)
    assert uc.reg_read(A.UC_ARM_REG_IPSR) == SYSTICK
    uc.emu_start(cpu.pc() | 1, 0xFFFFFFFE)
    assert cpu.exc_exit, "the handler should have returned through EXC_RETURN"
    assert uc.reg_read(A.UC_ARM_REG_R3) == 0x55, "the handler's first instruction ran under the IT condition"

    cpu.exit_exception()
    assert cpu.pc() == PAGE_END and uc.reg_read(A.UC_ARM_REG_IPSR) == 0
    uc.emu_start(cpu.pc() | 1, PAGE_END + 4)
    assert uc.reg_read(A.UC_ARM_REG_R1) == 0, "the IT block's 'eq' instruction ran: its condition was lost"
    assert uc.reg_read(A.UC_ARM_REG_R2) == 2
