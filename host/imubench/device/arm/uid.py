"""The 96-bit unique device ID and the flash size register in system memory.

F1: RM0008 30.1-30.2 (F_SIZE at 0x1FFFF7E0, UID at 0x1FFFF7E8); F4: RM0090 39.1-39.2 (UID at
0x1FFF7A10, F_SIZE at 0x1FFF7A22). The ID is the virtual device's (libimumodels.so derives
it from the seed, or --uid), mixed with the target (simlib_set_identity_salt) unless --uid gave
it: each target of a seed is a board of its own.
"""
from __future__ import annotations


class UniqueId:
    def __init__(self, page_base: int, uid_addr: int, fsize_addr: int, flash_kib: int, uid: bytes):
        self.mem = bytearray(0x400)
        self.page_base = page_base
        o = uid_addr - page_base
        self.mem[o:o + 12] = uid
        f = fsize_addr - page_base
        self.mem[f:f + 2] = flash_kib.to_bytes(2, "little")

    def read(self, off: int, size: int) -> int:
        return int.from_bytes(self.mem[off:off + size], "little")
