"""The Cortex-M CPU of the emulated board: the Unicorn engine (PyPI `unicorn`, QEMU's ARM
core as a library) in Thumb/M-profile mode as a Cortex-M3 (F103) or Cortex-M4 (F4), loaded
with the exact image (PT_LOAD segments of the ELF at their load addresses).

Unicorn executes instructions; it has no NVIC, so exception entry and return are done here,
the way Qiling's MCU support does it (qiling/arch/cortex_m.py: push the 8-word frame, set
IPSR, LR = EXC_RETURN, jump to the vector; catch the exception-exit Unicorn raises when the
handler branches to EXC_RETURN and unstack the frame by hand). We do the same steps rather
than depend on Qiling: it does not run with Unicorn 2.1 (docs/firmware.md) and single-steps
the CPU. Differences from hardware, all invisible to these images (no FPU use in handlers, no
PSP, no faults expected): the F4's caller-saved FP registers are saved by the emulator, not
in an extended frame; no tail-chaining or late-arrival timing; no fault escalation (a CPU
fault ends in the image's own HardFault handler, which resets the MCU).

Instructions are counted by a C block hook of libimumodels.so (simlib_block_hook), which also
stops the emulation at the instruction count of the next event; device time is derived from
the count (clock.py).
"""
from __future__ import annotations

import ctypes
import struct

from elftools.elf.elffile import ELFFile
from elftools.elf.sections import SymbolTableSection
from unicorn import (
    UC_ARCH_ARM,
    UC_HOOK_BLOCK,
    UC_HOOK_CODE,
    UC_HOOK_INTR,
    UC_MODE_MCLASS,
    UC_MODE_THUMB,
    UC_PROT_ALL,
    UC_PROT_EXEC,
    UC_PROT_READ,
    Uc,
    UcError,
)
from unicorn import arm_const as A

try:  # the raw library handle of the binding (unicorn >= 2.1 layout)
    from unicorn.unicorn_py3.unicorn import uc_hook_h, uclib
except ImportError:  # pragma: no cover - older layout
    from unicorn.unicorn import uc_hook_h, uclib  # type: ignore

_MMIO_READ = ctypes.CFUNCTYPE(ctypes.c_uint64, ctypes.c_void_p, ctypes.c_uint64, ctypes.c_uint, ctypes.c_void_p)
_MMIO_WRITE = ctypes.CFUNCTYPE(None, ctypes.c_void_p, ctypes.c_uint64, ctypes.c_uint, ctypes.c_uint64, ctypes.c_void_p)

EXC_RETURN_THREAD_MSP = 0xFFFFFFF9
XPSR_T = 1 << 24
XPSR_KEPT_ON_ENTRY = 0xF80F0000   # N Z C V Q and GE[3:0]: exception entry leaves them as they were
EXCP_EXCEPTION_EXIT = 8      # QEMU's EXCP_EXCEPTION_EXIT, reported through UC_HOOK_INTR
FRAME_REGS = (A.UC_ARM_REG_R0, A.UC_ARM_REG_R1, A.UC_ARM_REG_R2, A.UC_ARM_REG_R3, A.UC_ARM_REG_R12,
              A.UC_ARM_REG_LR, A.UC_ARM_REG_PC, A.UC_ARM_REG_XPSR)
FP_REGS = tuple(getattr(A, f"UC_ARM_REG_S{i}") for i in range(16))


class RegBatch:
    """Read/write a fixed list of 32-bit registers in one libunicorn call (the binding's
    per-register path costs several Python frames each; exception entry/return needs ~20)."""

    def __init__(self, uc, regs):
        self.uch = uc._uch
        self.n = len(regs)
        self.ids = (ctypes.c_int * self.n)(*regs)
        self.vals = (ctypes.c_uint64 * self.n)()
        base = ctypes.addressof(self.vals)
        self.ptrs = (ctypes.c_void_p * self.n)(*[base + 8 * i for i in range(self.n)])

    def read(self) -> list[int]:
        err = uclib.uc_reg_read_batch(self.uch, self.ids, self.ptrs, self.n)
        if err:
            raise RuntimeError(f"uc_reg_read_batch failed: {err}")
        return [v & 0xFFFFFFFF for v in self.vals]

    def write(self, values) -> None:
        for i, v in enumerate(values):
            self.vals[i] = v & 0xFFFFFFFF
        err = uclib.uc_reg_write_batch(self.uch, self.ids, self.ptrs, self.n)
        if err:
            raise RuntimeError(f"uc_reg_write_batch failed: {err}")


class Reg:
    """One 32-bit register read in one libunicorn call (the binding's reg_read looks up the
    register's class and builds a ctypes value on every call; PC and PRIMASK are read on
    every run segment and every exception check)."""

    def __init__(self, uc, reg):
        self.uch = uc._uch
        self.reg = reg
        self.val = ctypes.c_uint64()
        self.ref = ctypes.byref(self.val)

    def read(self) -> int:
        err = uclib.uc_reg_read(self.uch, self.reg, self.ref)
        if err:
            raise RuntimeError(f"uc_reg_read({self.reg}) failed: {err}")
        return self.val.value & 0xFFFFFFFF


class ElfImage:
    """Segments and symbols of the image."""

    def __init__(self, path: str):
        self.path = path
        self.segments: list[tuple[int, bytes]] = []
        self.symbols: dict[str, int] = {}
        self.func_sizes: dict[int, tuple[str, int]] = {}
        with open(path, "rb") as f:
            elf = ELFFile(f)
            for seg in elf.iter_segments():
                if seg["p_type"] == "PT_LOAD" and seg["p_filesz"] > 0:
                    self.segments.append((seg["p_paddr"], seg.data()[: seg["p_filesz"]]))
            for sec in elf.iter_sections():
                if isinstance(sec, SymbolTableSection):
                    for sym in sec.iter_symbols():
                        if sym.name and sym["st_info"]["type"] in ("STT_FUNC", "STT_OBJECT", "STT_NOTYPE"):
                            addr = sym["st_value"]
                            if sym["st_info"]["type"] == "STT_FUNC":
                                addr &= ~1
                                self.func_sizes[addr] = (sym.name, sym["st_size"])
                            self.symbols.setdefault(sym.name, addr)

    def struct_members(self, cu_suffix: str, struct: str) -> dict[str, int]:
        """Byte offsets of a struct's members, from the image's DWARF (the compilation unit
        whose name ends with cu_suffix)."""
        out: dict[str, int] = {}
        with open(self.path, "rb") as f:
            dw = ELFFile(f).get_dwarf_info()
            for cu in dw.iter_CUs():
                top = cu.get_top_DIE()
                name = top.attributes.get("DW_AT_name")
                if name is None or not name.value.decode().endswith(cu_suffix):
                    continue
                for die in top.iter_children():
                    n = die.attributes.get("DW_AT_name")
                    if die.tag == "DW_TAG_structure_type" and n is not None and n.value.decode() == struct:
                        for mem in die.iter_children():
                            if mem.tag == "DW_TAG_member" and "DW_AT_data_member_location" in mem.attributes:
                                out[mem.attributes["DW_AT_name"].value.decode()] = \
                                    mem.attributes["DW_AT_data_member_location"].value
                        return out
        raise KeyError(f"{self.path}: no struct {struct} in {cu_suffix} (built without -g?)")

    def sym(self, name: str) -> int:
        try:
            return self.symbols[name]
        except KeyError:
            raise KeyError(f"{self.path} has no symbol {name!r}: not an imubench image?") from None


class Cpu:
    def __init__(self, machine, target, image: ElfImage, lib):
        self.m = machine
        self.t = target
        self.img = image
        self.lib = lib
        uc = Uc(UC_ARCH_ARM, UC_MODE_THUMB | UC_MODE_MCLASS)
        uc.ctl_set_cpu_model(A.UC_CPU_ARM_CORTEX_M3 if target.cpu == "cortex-m3" else A.UC_CPU_ARM_CORTEX_M4)
        self.uc = uc
        self.exc_exit = False
        self.wfi = False
        self.fp_saved: list[list[int] | None] = []
        self._hooks = []
        # exception entry reads the frame + SP + CONTROL, writes SP, xPSR, IPSR, LR, PC
        self._rd_entry = RegBatch(uc, list(FRAME_REGS) + [A.UC_ARM_REG_SP, A.UC_ARM_REG_CONTROL])
        self._wr_entry = RegBatch(uc, [A.UC_ARM_REG_SP, A.UC_ARM_REG_XPSR, A.UC_ARM_REG_IPSR, A.UC_ARM_REG_LR,
                                       A.UC_ARM_REG_PC])
        self._rd_sp = RegBatch(uc, [A.UC_ARM_REG_SP])
        self._wr_exit = RegBatch(uc, list(FRAME_REGS[:7]) + [A.UC_ARM_REG_SP, A.UC_ARM_REG_XPSR, A.UC_ARM_REG_IPSR,
                                                             A.UC_ARM_REG_PC])
        self._fp = RegBatch(uc, list(FP_REGS) + [A.UC_ARM_REG_FPSCR]) if target.cpu == "cortex-m4" else None
        self._ctrl = RegBatch(uc, [A.UC_ARM_REG_CONTROL])
        self._pc = Reg(uc, A.UC_ARM_REG_PC)
        self._primask = Reg(uc, A.UC_ARM_REG_PRIMASK)
        self._words = {n: ctypes.create_string_buffer(n) for n in (4, 32)}

    # ---------------------------------------------------------------- memory
    def map_memory(self, mmio_regions: list[tuple[int, int, object, object]]) -> None:
        t, uc = self.t, self.uc
        code_size = t.param_base - t.flash_base
        uc.mem_map(t.flash_base, code_size, UC_PROT_READ | UC_PROT_EXEC)
        uc.mem_map(t.ram_base, t.ram_size, UC_PROT_ALL)
        hi = t.param_base + t.param_size                 # flash above the parameter pages (F103CB: the
        if hi < t.flash_base + t.flash_size:             # upper 64 KiB no image uses) reads erased
            uc.mem_map(hi, t.flash_base + t.flash_size - hi, UC_PROT_READ | UC_PROT_EXEC)
            uc.mem_write(hi, b"\xff" * (t.flash_base + t.flash_size - hi))
        # Raw ctypes callbacks (not Uc.mmio_map's wrappers): an MMIO access is the hot path
        # of the emulation (~200 per sample), every Python frame counts. The callbacks get
        # (offset, size[, value]); an exception in one is a bug in a peripheral model: it is
        # logged and the access reads 0.
        self._mmio_refs = []
        for base, size, rd, wr in mmio_regions:
            rcb = _MMIO_READ(lambda _uc, off, sz, _ud, rd=rd: self._guard_rd(rd, off, sz))
            wcb = _MMIO_WRITE(lambda _uc, off, sz, val, _ud, wr=wr: self._guard_wr(wr, off, sz, val))
            self._mmio_refs += [rcb, wcb]
            err = uclib.uc_mmio_map(uc._uch, base, size, ctypes.cast(rcb, ctypes.c_void_p), None,
                                    ctypes.cast(wcb, ctypes.c_void_p), None)
            if err != 0:
                raise RuntimeError(f"uc_mmio_map(0x{base:08X}) failed: {err}")
        for addr, data in self.img.segments:
            if t.flash_base <= addr < t.param_base or t.ram_base <= addr < t.ram_base + t.ram_size:
                uc.mem_write(addr, data)
            else:
                raise ValueError(f"{self.img.path}: segment at 0x{addr:08X} outside the {t.name} memory map")
        # the code as half-words for the instruction counter
        raw = bytes(uc.mem_read(t.flash_base, code_size))
        self.code = (ctypes.c_uint16 * (code_size // 2)).from_buffer_copy(raw)
        self.code_bytes = raw

    def _guard_rd(self, rd, off, size):
        try:
            return rd(off, size)
        except Exception as e:  # noqa: BLE001 - keep the CPU running, report the model bug
            self.m.model_error(e)
            return 0

    def _guard_wr(self, wr, off, size, value):
        try:
            wr(off, size, value)
        except Exception as e:  # noqa: BLE001
            self.m.model_error(e)

    def install_counter(self, regions: bytearray) -> None:
        self.region_map = (ctypes.c_uint8 * len(regions)).from_buffer(regions)
        stop = ctypes.cast(uclib.uc_emu_stop, ctypes.c_void_p)
        self.lib.simlib_counter_setup(stop, self.code, self.t.flash_base, len(self.code), self.region_map)
        handle = uc_hook_h()
        cb = ctypes.cast(self.lib.simlib_block_hook, ctypes.c_void_p)
        err = uclib.uc_hook_add(self.uc._uch, ctypes.byref(handle), UC_HOOK_BLOCK, cb, None,
                                ctypes.c_uint64(1), ctypes.c_uint64(0))
        if err != 0:
            raise RuntimeError(f"uc_hook_add(UC_HOOK_BLOCK) failed: {err}")
        self.uc.hook_add(UC_HOOK_INTR, self._on_intr)

    def hook_at(self, addr: int, fn) -> None:
        """fn() when the instruction at addr is about to execute."""
        self._hooks.append(self.uc.hook_add(UC_HOOK_CODE, lambda uc, a, s, d: fn(), None, addr, addr))

    def wfi_addresses(self) -> list[int]:
        """Half-words that encode WFI (0xBF30) in the code; a hook there only fires if one is
        executed as an instruction."""
        out = []
        raw = self.code_bytes
        for i in range(0, len(raw) - 1, 2):
            if raw[i] == 0x30 and raw[i + 1] == 0xBF:
                out.append(self.t.flash_base + i)
        return out

    def unmask_addresses(self) -> list[int]:
        """Half-words that start an instruction able to clear PRIMASK: MSR PRIMASK, Rn
        (0xF38n 0x8810) and CPSIE i (0xB662)."""
        out = []
        raw = self.code_bytes
        for i in range(0, len(raw) - 3, 2):
            hw = raw[i] | raw[i + 1] << 8
            if hw == 0xB662 or ((hw & 0xFFF0) == 0xF380 and (raw[i + 2] | raw[i + 3] << 8) == 0x8810):
                out.append(self.t.flash_base + i)
        return out

    def _on_intr(self, uc, intno, data) -> None:
        if intno == EXCP_EXCEPTION_EXIT:
            self.exc_exit = True
        else:
            self.m.cpu_fault(f"CPU exception {intno} at pc 0x{uc.reg_read(A.UC_ARM_REG_PC):08X}")
        uc.emu_stop()

    def on_wfi(self) -> None:
        self.wfi = True
        self.m.stop_soon()

    # ------------------------------------------------------------- registers
    def reset(self) -> None:
        uc = self.uc
        vec = self.t.flash_base
        sp, pc = struct.unpack("<II", bytes(uc.mem_read(vec, 8)))
        for r in range(13):
            uc.reg_write(getattr(A, f"UC_ARM_REG_R{r}"), 0)
        uc.reg_write(A.UC_ARM_REG_PRIMASK, 0)
        uc.reg_write(A.UC_ARM_REG_BASEPRI, 0)
        uc.reg_write(A.UC_ARM_REG_CONTROL, 0)
        uc.reg_write(A.UC_ARM_REG_IPSR, 0)
        uc.reg_write(A.UC_ARM_REG_MSP, sp)
        uc.reg_write(A.UC_ARM_REG_SP, sp)
        uc.reg_write(A.UC_ARM_REG_LR, 0xFFFFFFFF)
        uc.reg_write(A.UC_ARM_REG_PC, pc & ~1)
        self.exc_exit = False
        self.wfi = False
        self.fp_saved = []

    def pc(self) -> int:
        return self._pc.read()

    def primask(self) -> int:
        return self._primask.read() & 1

    def _read(self, addr: int, n: int) -> bytes:
        """n (4 or 32) bytes of memory in one libunicorn call into a buffer kept for it."""
        buf = self._words[n]
        err = uclib.uc_mem_read(self.uc._uch, addr, buf, n)
        if err:
            raise UcError(err)
        return buf.raw

    def run(self) -> None:
        """Run from the current PC until the block hook's limit, emu_stop or an error. What
        Uc.emu_start does, without its Python frame: an exception raised in a Python hook
        (the binding keeps it in _hook_exception) is raised here."""
        uc = self.uc
        uc._hook_exception = None
        err = uclib.uc_emu_start(uc._uch, self._pc.read() | 1, 0xFFFFFFFE, 0, 0)
        if err:
            raise UcError(err)
        if uc._hook_exception is not None:
            raise uc._hook_exception

    # ------------------------------------------------------------ exceptions
    def enter_exception(self, exc: int, vtor: int) -> None:
        """Exception entry (ARMv7-M ARM B1.5.6 PushStack + ExceptionTaken)."""
        uc = self.uc
        vals = self._rd_entry.read()
        sp, control = vals[8], vals[9]
        frame = vals[:8]
        xpsr = frame[7]
        if sp & 4:                       # CCR.STKALIGN: 8-byte aligned frame, flag in xPSR[9]
            sp -= 4
            xpsr |= 1 << 9
        sp -= 32
        frame[7] = xpsr
        uc.mem_write(sp, struct.pack("<8I", *frame))
        if self._fp is not None and control & 4:
            # CONTROL.FPCA: the interrupted code has an active FP context. Hardware would
            # stack s0-s15/FPSCR in an extended frame (EXC_RETURN 0xFFFFFFE9); we keep them
            # aside and restore them on return, which no handler can tell apart.
            self.fp_saved.append(self._fp.read() + [control])
            self._ctrl.write([control & ~4])
        else:
            self.fp_saved.append(None)
        handler = struct.unpack("<I", self._read(vtor + 4 * exc, 4))[0]
        # The handler starts with EPSR.IT cleared (B1.5.6: ITSTATE = 0) and T set; the
        # flags (N Z C V Q, GE) are kept. Unicorn keeps the interrupted code's IT state
        # otherwise: stopped inside an IT block (a translation block ends at a 1 KB page),
        # the handler's first instructions would run as that block's conditional ones.
        # The stacked xPSR (Unicorn's XPSR read includes IT) gives it back on return.
        entry_xpsr = (frame[7] & XPSR_KEPT_ON_ENTRY) | XPSR_T | exc
        self._wr_entry.write([sp, entry_xpsr, exc, EXC_RETURN_THREAD_MSP, handler & ~1])

    def exit_exception(self) -> None:
        """Exception return through EXC_RETURN (B1.5.8 ExceptionReturn + PopStack)."""
        self.exc_exit = False
        sp = self._rd_sp.read()[0]
        vals = struct.unpack("<8I", self._read(sp, 32))
        sp += 32
        if vals[7] & (1 << 9):
            sp += 4
        self._wr_exit.write(list(vals[:7]) + [sp, vals[7] & ~(1 << 9), vals[7] & 0x1FF, vals[6] & ~1])
        fp = self.fp_saved.pop() if self.fp_saved else None
        if fp is not None:
            self._fp.write(fp[:17])
            self._ctrl.write([fp[17]])
