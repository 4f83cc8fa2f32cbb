"""USART1 (RM0008 27.6 / RM0090 30.6: SR, DR, BRR, CR1, CR2, CR3, GTPR), 8N1 as the images
use it, connected to the serial endpoint of libimumodels.so (socket://, with the virtual
device's link faults and statistics).

Baud rate: f_PCLK2 / USARTDIV with BRR = USARTDIV x 16 (16x oversampling; OVER8 on the F4
halves it). A frame is 1 start + 8 data + 1 stop bit (CR1.M = 0, CR2.STOP = 00).

Transmit: TDR + shift register. A byte written to DR (by the core or by the TX DMA) starts
shifting when the shift register is free and is on the wire one frame time later; TXE is
clear while TDR holds a byte that has not started, TC is set when the last byte has left
(cleared by SR-read-then-DR-write or by writing 0). Bytes that have left are handed to the
endpoint in batches, in order.
Receive: bytes from the endpoint arrive one frame time apart (no earlier than the device
time they were received at); each sets RXNE (interrupt with RXNEIE); a byte arriving while
RXNE is still set is lost and sets ORE, as on hardware. SR-then-DR read clears RXNE, ORE,
FE, NE. No parity, break, LIN, IrDA, smartcard, hardware flow control or noise is modelled.
"""
from __future__ import annotations

import collections
import ctypes

SR_PE, SR_FE, SR_NE, SR_ORE, SR_IDLE, SR_RXNE, SR_TC, SR_TXE = (1 << i for i in (0, 1, 2, 3, 4, 5, 6, 7))
CR1_RE, CR1_TE, CR1_RXNEIE, CR1_TCIE, CR1_TXEIE, CR1_UE = 1 << 2, 1 << 3, 1 << 5, 1 << 6, 1 << 7, 1 << 13
CR3_DMAT = 1 << 7


class Usart:
    def __init__(self, machine, lib, irq: int):
        self.m = machine
        self.lib = lib
        self.irq = irq
        self.tx_bytes = 0
        self.rx_bytes = 0
        self.rx_overruns = 0
        self._buf = (ctypes.c_uint8 * 1)()
        self.reset()

    def reset(self) -> None:
        self.cr1 = self.cr2 = self.cr3 = 0
        self.brr = 0
        self.gtpr = 0
        self.out: collections.deque = collections.deque()   # (end time, byte) not yet handed over
        self.line_free = 0.0          # end of the last queued frame
        self.last_start = -1.0        # start of the last queued frame
        self.tc_cleared = False
        self.sr_read = False
        self.rx_dr = 0
        self.rxne = False
        self.ore = False
        self.rx_next: tuple[float, int] | None = None   # (arrival time, byte)
        self.rx_line_free = 0.0

    def frame_time(self) -> float:
        brr = max(self.brr, 16)
        div = brr / 16.0
        over8 = self.cr1 & (1 << 15)      # F4 only: the F1's CR1 bit 15 is reserved (masked)
        baud = self.m.rcc.pclk2_hz() / ((8 if over8 else 16) * div)
        return 10.0 / baud

    def baud(self) -> float:
        return 10.0 / self.frame_time()

    def enabled_tx(self) -> bool:
        return bool(self.cr1 & CR1_UE and self.cr1 & CR1_TE)

    # ------------------------------------------------------------ transmit
    def queue(self, data: bytes, t: float) -> list[float]:
        """Bytes written to TDR from t on (DMA: back to back as TXE allows). Returns each
        byte's write time (when TDR took it)."""
        ft = self.frame_time()
        writes = []
        for b in data:
            w = max(t, self.last_start)      # TDR free once the previous byte started
            start = max(w, self.line_free)
            self.last_start = start
            self.line_free = start + ft
            self.out.append((self.line_free, b))
            writes.append(w)
            t = w
        self.tc_cleared = False
        self.m.events_changed()
        return writes

    def truncate_after(self, t: float) -> int:
        """DMA stopped: drop queued bytes TDR had not taken by t. Returns how many."""
        kept = collections.deque()
        dropped = 0
        prev_start = -1.0
        ft = self.frame_time()
        for end, b in self.out:
            start = end - ft
            if prev_start <= t:
                kept.append((end, b))
                prev_start = start
            else:
                dropped += 1
        if dropped:
            self.out = kept
            self.line_free = kept[-1][0] if kept else min(self.line_free, t)
            self.last_start = self.line_free - ft if kept else -1.0
        return dropped

    def drain(self, t: float) -> None:
        """Hand the bytes that have left by t to the endpoint."""
        if not self.out or self.out[0][0] > t:
            return
        chunk = bytearray()
        while self.out and self.out[0][0] <= t:
            chunk.append(self.out.popleft()[1])
        self.tx_bytes += len(chunk)
        self.m.set_model_time(t)
        self.lib.simlib_link_push(bytes(chunk), len(chunk))

    def txe(self, t: float) -> bool:
        return self.last_start <= t

    def tc(self, t: float) -> bool:
        return t >= self.line_free and not self.tc_cleared

    # ------------------------------------------------------------- receive
    def update(self, t: float) -> None:
        self.drain(t)
        while self.rx_next is not None and self.rx_next[0] <= t:
            arrival, b = self.rx_next
            self.rx_next = None
            if self.rxne:
                self.ore = True
                self.rx_overruns += 1
            else:
                self.rx_dr = b
                self.rxne = True
            self.rx_bytes += 1
            self._irq_check()
            self.schedule_rx(arrival)

    def schedule_rx(self, t: float) -> None:
        """Take the next received byte from the endpoint if the line is free."""
        if self.rx_next is not None or not (self.cr1 & CR1_UE and self.cr1 & CR1_RE):
            return
        if self.lib.simlib_link_rx_pending() == 0:
            return
        if self.lib.simlib_link_pull(self._buf, 1) != 1:
            return
        arrival = max(t, self.rx_line_free) + self.frame_time()
        self.rx_line_free = arrival
        self.rx_next = (arrival, self._buf[0])
        self.m.events_changed()

    def next_event(self) -> float:
        """The next received byte (bytes leaving are handed over lazily, not as events)."""
        return self.rx_next[0] if self.rx_next is not None else float("inf")

    def _irq_check(self) -> None:
        if (self.cr1 & CR1_RXNEIE and (self.rxne or self.ore)):
            self.m.nvic.pend_irq(self.irq)
        if self.cr1 & (CR1_TCIE | CR1_TXEIE):
            t = self.m.now()
            if (self.cr1 & CR1_TCIE and self.tc(t)) or (self.cr1 & CR1_TXEIE and self.txe(t)):
                self.m.nvic.pend_irq(self.irq)

    # ------------------------------------------------------------ registers
    def read(self, off: int, size: int, t: float) -> int:
        self.update(t)
        if off == 0x0:
            sr = 0
            if self.txe(t):
                sr |= SR_TXE
            if self.tc(t):
                sr |= SR_TC
            if self.rxne:
                sr |= SR_RXNE
            if self.ore:
                sr |= SR_ORE
            self.sr_read = True
            return sr
        if off == 0x4:
            v = self.rx_dr
            self.rxne = False
            if self.sr_read:
                self.ore = False
            self.sr_read = False
            self.schedule_rx(t)
            return v
        return {0x8: self.brr, 0xC: self.cr1, 0x10: self.cr2, 0x14: self.cr3, 0x18: self.gtpr}.get(off, 0)

    def write(self, off: int, size: int, value: int, t: float) -> None:
        self.update(t)
        if off == 0x4:
            if not self.enabled_tx():
                self.m.log("USART1: DR written with the transmitter disabled: byte dropped")
                return
            if self.sr_read:
                self.tc_cleared = False
            self.queue(bytes([value & 0xFF]), t)
        elif off == 0x0:
            if not value & SR_TC:
                self.tc_cleared = True
            if not value & SR_RXNE:
                self.rxne = False
        elif off == 0x8:
            self.brr = value & 0xFFFF
        elif off == 0xC:
            self.cr1 = value & (0xBFFF if self.m.target.name == "f4" else 0x3FFF)
            self.schedule_rx(t)
            self._irq_check()
        elif off == 0x10:
            self.cr2 = value & 0x7F6F
            if value & 0x3000:
                self.m.log("USART1: stop bits other than 1 are not modelled")
        elif off == 0x14:
            self.cr3 = value & (0xFFF if self.m.target.name == "f4" else 0x7FF)   # ONEBIT: F4 only
        elif off == 0x18:
            self.gtpr = value & 0xFFFF
        else:
            self.m.unmodelled("USART1", off, size, value)
        self.sr_read = False
