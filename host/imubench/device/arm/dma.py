"""The DMA channels the images use: USART1 TX (memory to peripheral) and SPI1 RX/TX (a
full-duplex SPI transfer by DMA), byte wide.

F1: DMA1 (RM0008 13.4: ISR, IFCR, CCRx, CNDTRx, CPARx, CMARx); USART1_TX is channel 4
(table 78), interrupt DMA1_Channel4 (IRQ 14).
F4: DMA2 (RM0090 10.5: LISR, HISR, LIFCR, HIFCR, SxCR, SxNDTR, SxPAR, SxM0AR, SxM1AR, SxFCR);
USART1_TX is stream 7 channel 4 (table 43), interrupt DMA2_Stream7 (IRQ 70). EN reads 1
while the stream runs and is cleared by hardware at the end of the transfer.

When the channel is enabled with DIR = memory-to-peripheral, CPAR = USART1 DR and the USART's
CR3.DMAT set, it moves NDTR bytes from memory (MINC) into USART1 DR each time TXE is set:
the bytes' times come from the USART's frame time (usart.queue), NDTR counts down with them,
HTIF/TCIF are set at half/whole transfer (with TCIE/HTIE: the interrupt), and the channel
reads the bytes from SRAM when it starts (the image does not touch queued bytes).

SPI1 by DMA: F1 DMA1 channel 2 = SPI1_RX, channel 3 = SPI1_TX (RM0008 table 78); F4 DMA2
stream 0 channel 3 = SPI1_RX, stream 3 channel 3 = SPI1_TX (RM0090 table 43). Once both are
enabled towards SPI1 DR (RX peripheral-to-memory, TX memory-to-peripheral, the same NDTR) and
SPI1 CR2 has RXDMAEN and TXDMAEN, the SPI clocks the NDTR bytes back to back (spi.dma_exchange:
the same sensor models, one SPI frame time per byte, so the bus time elapses in device time);
at the end of the last frame the received bytes are in memory (MINC, or the last byte at a
fixed address), both channels' TCIF are set (TCIE: the interrupt), NDTR reads 0 and, on the
F4, EN clears. While it runs NDTR counts down with the frames. Other channels/streams keep
their register values and move nothing (the images use none).
"""
from __future__ import annotations

import bisect


class _Transfer:
    def __init__(self, writes: list[float], n: int):
        self.writes = writes   # device time each byte was written to USART DR
        self.n = n
        self.t_half = writes[(n - 1) // 2] if n else 0.0
        self.t_end = writes[-1] if n else 0.0

    def done_by(self, t: float) -> int:
        return bisect.bisect_right(self.writes, t)


class _SpiJob:
    def __init__(self, t0: float, t_end: float, n: int, rx_addr: int, rx_minc: bool):
        self.t0, self.t_end, self.n = t0, t_end, n
        self.rx_addr, self.rx_minc = rx_addr, rx_minc

    def remaining(self, t: float) -> int:
        if t >= self.t_end:
            return 0
        done = int(self.n * (t - self.t0) / (self.t_end - self.t0)) if self.t_end > self.t0 else self.n
        return max(0, self.n - done)


class _TxDma:
    """What both chips' TX channel does; subclasses map the registers."""

    def __init__(self, machine, usart, irq: int, usart_dr: int):
        self.m = machine
        self.usart = usart
        self.irq = irq
        self.usart_dr = usart_dr
        self.xfer: _Transfer | None = None
        self.flags = 0      # TCIF | HTIF | TEIF as bit 0/1/2 of our own
        self.transfers = 0
        self.spi_job: _SpiJob | None = None
        self.spi_flags = {0: 0, 1: 0}   # SPI RX (0) / TX (1) channel: TCIF | HTIF | TEIF bits 0/1/2
        self.spi_transfers = 0

    # ---- SPI1 RX/TX (subclasses say where their channels' registers are)
    SPI_DR = 0x4001300C

    def _spi_chan(self, which: int) -> dict:
        """en, mem, minc, ndtr, ok (direction/channel/peripheral as SPI1 needs) of the RX
        (0) or TX (1) channel."""
        raise NotImplementedError

    def _spi_finished(self) -> None:
        raise NotImplementedError

    def _spi_irq(self, which: int) -> None:
        raise NotImplementedError

    def spi_try_start(self, t: float) -> None:
        if self.spi_job is not None:
            return
        rx, tx = self._spi_chan(0), self._spi_chan(1)
        spi = self.m.spi
        if not (rx["en"] and tx["en"] and (spi.cr2 & 3) == 3):
            return
        if not (rx["ok"] and tx["ok"]):
            self.m.log("DMA: SPI1 channels enabled with a direction/peripheral SPI1 does not request: no requests")
            return
        n = tx["ndtr"]
        if n == 0 or rx["ndtr"] != n:
            self.m.log(f"DMA: SPI1 RX/TX counts differ ({rx['ndtr']} / {n}): not modelled")
            return
        try:
            data = bytes(self.m.cpu.uc.mem_read(tx["mem"], n)) if tx["minc"] else \
                bytes(self.m.cpu.uc.mem_read(tx["mem"], 1)) * n
        except Exception:  # noqa: BLE001 - unmapped memory: a transfer error
            self.spi_flags[1] |= 4
            self._spi_irq(1)
            return
        t_end = spi.dma_exchange(data, t)
        self.spi_job = _SpiJob(t, t_end, n, rx["mem"], rx["minc"])
        self.spi_transfers += 1
        self.m.events_changed()

    def spi_abort(self, t: float) -> None:
        if self.spi_job is not None and t < self.spi_job.t_end:
            self.m.log("DMA: SPI1 channel disabled while its transfer ran: the bytes clocked so far stay")
        self.spi_job = None

    def _spi_update(self, t: float) -> None:
        j = self.spi_job
        if j is None or t < j.t_end:
            return
        self.spi_job = None
        got = self.m.spi.dma_received(j.n)
        try:
            if j.rx_minc:
                self.m.cpu.uc.mem_write(j.rx_addr, got)
            else:
                self.m.cpu.uc.mem_write(j.rx_addr, got[-1:])
        except Exception:  # noqa: BLE001
            self.spi_flags[0] |= 4
        self.spi_flags[0] |= 3
        self.spi_flags[1] |= 3
        self._spi_finished()
        self._spi_irq(0)
        self._spi_irq(1)

    def _start(self, mem: int, par: int, n: int, t: float) -> None:
        if n == 0:
            return
        if par != self.usart_dr or not self.usart.cr3 & (1 << 7):
            self.m.log(f"DMA: TX channel started towards 0x{par:08X} without USART1 DMAT: no requests")
            return
        try:
            data = bytes(self.m.cpu.uc.mem_read(mem, n))
        except Exception:  # noqa: BLE001 - a transfer from unmapped memory is a transfer error
            self.flags |= 4
            self._irq_check()
            return
        self.xfer = _Transfer(self.usart.queue(data, t), n)
        self.transfers += 1
        self.m.events_changed()

    def update(self, t: float) -> None:
        self._spi_update(t)
        x = self.xfer
        if x is None:
            return
        if t >= x.t_half:
            self.flags |= 2
        if t >= x.t_end:
            self.flags |= 1
            self.xfer = None
            self._finished()
        self._irq_check()

    def next_event(self) -> float:
        js = self.spi_job.t_end if self.spi_job is not None else float("inf")
        x = self.xfer
        if x is None:
            return js
        return min(js, x.t_half if not self.flags & 2 and x.t_half > self.m.now() else x.t_end)

    def remaining(self, t: float) -> int:
        x = self.xfer
        return x.n - x.done_by(t) if x is not None else 0

    def stop(self, t: float) -> None:
        if self.xfer is not None:
            self.usart.truncate_after(t)
            self.xfer = None

    def _finished(self) -> None:
        pass

    def _irq_check(self) -> None:
        raise NotImplementedError


class DmaF1(_TxDma):
    CH = 4
    SPI_CH = (2, 3)          # SPI1_RX, SPI1_TX (RM0008 table 78)
    SPI_IRQ = (12, 13)       # DMA1_Channel2, DMA1_Channel3 (RM0008 table 63)

    def __init__(self, machine, usart, irq: int, usart_dr: int):
        super().__init__(machine, usart, irq, usart_dr)
        self.reset()

    def reset(self) -> None:
        self.ccr = [0] * 8
        self.cndtr = [0] * 8
        self.cpar = [0] * 8
        self.cmar = [0] * 8
        self.isr_other = 0
        self.xfer = None
        self.flags = 0
        self.spi_job = None
        self.spi_flags = {0: 0, 1: 0}

    def _finished(self) -> None:
        self.cndtr[self.CH] = 0   # the channel stays enabled with nothing left to move

    def _spi_chan(self, which: int) -> dict:
        ch = self.SPI_CH[which]
        c = self.ccr[ch]
        ok = self.cpar[ch] == self.SPI_DR and (c >> 4) & 1 == which and (c >> 8) & 0xF == 0
        return {"en": c & 1, "mem": self.cmar[ch], "minc": bool(c & 0x80), "ndtr": self.cndtr[ch], "ok": ok}

    def _spi_finished(self) -> None:
        for ch in self.SPI_CH:
            self.cndtr[ch] = 0

    def _spi_irq(self, which: int) -> None:
        c, f = self.ccr[self.SPI_CH[which]], self.spi_flags[which]
        if (f & 1 and c & 2) or (f & 2 and c & 4) or (f & 4 and c & 8):
            self.m.nvic.pend_irq(self.SPI_IRQ[which])

    def _irq_check(self) -> None:
        c = self.ccr[self.CH]
        if (self.flags & 1 and c & 2) or (self.flags & 2 and c & 4) or (self.flags & 4 and c & 8):
            self.m.nvic.pend_irq(self.irq)

    def _isr(self) -> int:
        f = self.flags
        bits = (1 if f else 0) | (2 if f & 1 else 0) | (4 if f & 2 else 0) | (8 if f & 4 else 0)
        out = self.isr_other | (bits << (4 * (self.CH - 1)))
        for which, ch in enumerate(self.SPI_CH):
            g = self.spi_flags[which]
            b = (1 if g else 0) | (2 if g & 1 else 0) | (4 if g & 2 else 0) | (8 if g & 4 else 0)
            out |= b << (4 * (ch - 1))
        return out

    def read(self, off: int, size: int, t: float) -> int:
        self.update(t)
        if off == 0x0:
            return self._isr()
        if off == 0x4:
            return 0
        ch, reg = (off - 0x08) // 20 + 1, (off - 0x08) % 20
        if not 1 <= ch <= 7:
            self.m.unmodelled("DMA1", off, size, None)
            return 0
        if reg == 0x0:
            return self.ccr[ch]
        if reg == 0x4:
            if ch in self.SPI_CH and self.spi_job is not None:
                return self.spi_job.remaining(t)
            return self.remaining(t) if ch == self.CH and self.xfer is not None else self.cndtr[ch]
        if reg == 0x8:
            return self.cpar[ch]
        if reg == 0xC:
            return self.cmar[ch]
        return 0

    def write(self, off: int, size: int, value: int, t: float) -> None:
        self.update(t)
        if off == 0x4:
            mine = (value >> (4 * (self.CH - 1))) & 0xF
            if mine & 1:
                self.flags = 0
            else:
                self.flags &= ~((mine >> 1) & 7)
            for which, ch in enumerate(self.SPI_CH):
                m = (value >> (4 * (ch - 1))) & 0xF
                if m & 1:
                    self.spi_flags[which] = 0
                else:
                    self.spi_flags[which] &= ~((m >> 1) & 7)
            return
        ch, reg = (off - 0x08) // 20 + 1, (off - 0x08) % 20
        if off < 0x08 or not 1 <= ch <= 7:
            self.m.unmodelled("DMA1", off, size, value)
            return
        if reg == 0x0:
            was = self.ccr[ch] & 1
            self.ccr[ch] = value & 0x7FFF
            if ch == self.CH:
                if was and not value & 1:
                    self.cndtr[ch] = self.remaining(t)
                    self.stop(t)
                elif not was and value & 1:
                    if not value & (1 << 4):
                        self.m.log("DMA1 ch4: peripheral-to-memory is not modelled")
                    else:
                        self._start(self.cmar[ch], self.cpar[ch], self.cndtr[ch], t)
                self._irq_check()
            elif ch in self.SPI_CH:
                if was and not value & 1:
                    self.spi_abort(t)
                elif not was and value & 1:
                    self.spi_try_start(t)
        elif reg == 0x4:
            if not self.ccr[ch] & 1:
                self.cndtr[ch] = value & 0xFFFF
        elif reg == 0x8:
            if not self.ccr[ch] & 1:
                self.cpar[ch] = value
        elif reg == 0xC:
            if not self.ccr[ch] & 1:
                self.cmar[ch] = value


class DmaF4(_TxDma):
    S = 7
    SPI_S = (0, 3)           # SPI1_RX stream 0, SPI1_TX stream 3, both channel 3 (RM0090 table 43)
    SPI_SHIFT = (0, 22)      # their flags' position in LISR/LIFCR
    SPI_IRQ = (56, 59)       # DMA2_Stream0, DMA2_Stream3 (RM0090 table 61)
    # HISR/HIFCR bit of each stream-7 flag
    FEIF, DMEIF, TEIF, HTIF, TCIF = 1 << 22, 1 << 24, 1 << 25, 1 << 26, 1 << 27

    def __init__(self, machine, usart, irq: int, usart_dr: int):
        super().__init__(machine, usart, irq, usart_dr)
        self.reset()

    def reset(self) -> None:
        self.scr = [0] * 8
        self.sndtr = [0] * 8
        self.spar = [0] * 8
        self.sm0ar = [0] * 8
        self.sm1ar = [0] * 8
        self.sfcr = [0x21] * 8
        self.xfer = None
        self.flags = 0
        self.spi_job = None
        self.spi_flags = {0: 0, 1: 0}

    def _finished(self) -> None:
        self.scr[self.S] &= ~1   # EN cleared by hardware at the end of the transfer
        self.sndtr[self.S] = 0

    def _spi_chan(self, which: int) -> dict:
        s = self.SPI_S[which]
        c = self.scr[s]
        ok = (self.spar[s] == self.SPI_DR and (c >> 6) & 3 == which and (c >> 25) & 7 == 3
              and (c >> 11) & 0xF == 0)
        return {"en": c & 1, "mem": self.sm0ar[s], "minc": bool(c & (1 << 10)), "ndtr": self.sndtr[s], "ok": ok}

    def _spi_finished(self) -> None:
        for s in self.SPI_S:
            self.scr[s] &= ~1
            self.sndtr[s] = 0

    def _spi_irq(self, which: int) -> None:
        c, f = self.scr[self.SPI_S[which]], self.spi_flags[which]
        if (f & 1 and c & 0x10) or (f & 2 and c & 0x8) or (f & 4 and c & 0x4):
            self.m.nvic.pend_irq(self.SPI_IRQ[which])

    def _lisr(self) -> int:
        out = 0
        for which, sh in enumerate(self.SPI_SHIFT):
            f = self.spi_flags[which]
            out |= ((1 << 5) if f & 1 else 0) << sh | ((1 << 4) if f & 2 else 0) << sh | \
                ((1 << 3) if f & 4 else 0) << sh
        return out

    def _irq_check(self) -> None:
        c = self.scr[self.S]
        if (self.flags & 1 and c & 0x10) or (self.flags & 2 and c & 0x8) or (self.flags & 4 and c & 0x4):
            self.m.nvic.pend_irq(self.irq)

    def _hisr(self) -> int:
        f = self.flags
        return (self.TCIF if f & 1 else 0) | (self.HTIF if f & 2 else 0) | (self.TEIF if f & 4 else 0)

    def read(self, off: int, size: int, t: float) -> int:
        self.update(t)
        if off == 0x0:
            return self._lisr()
        if off == 0x4:
            return self._hisr()
        if off in (0x8, 0xC):
            return 0
        s, reg = (off - 0x10) // 0x18, (off - 0x10) % 0x18
        if off < 0x10 or not 0 <= s <= 7:
            self.m.unmodelled("DMA2", off, size, None)
            return 0
        if reg == 0x0:
            return self.scr[s]
        if reg == 0x4:
            if s in self.SPI_S and self.spi_job is not None:
                return self.spi_job.remaining(t)
            return self.remaining(t) if s == self.S and self.xfer is not None else self.sndtr[s]
        return {0x8: self.spar, 0xC: self.sm0ar, 0x10: self.sm1ar, 0x14: self.sfcr}[reg][s]

    def write(self, off: int, size: int, value: int, t: float) -> None:
        self.update(t)
        if off == 0xC:   # HIFCR
            if value & self.TCIF:
                self.flags &= ~1
            if value & self.HTIF:
                self.flags &= ~2
            if value & self.TEIF:
                self.flags &= ~4
            return
        if off == 0x8:   # LIFCR
            for which, sh in enumerate(self.SPI_SHIFT):
                m = value >> sh
                if m & (1 << 5):
                    self.spi_flags[which] &= ~1
                if m & (1 << 4):
                    self.spi_flags[which] &= ~2
                if m & (1 << 3):
                    self.spi_flags[which] &= ~4
            return
        s, reg = (off - 0x10) // 0x18, (off - 0x10) % 0x18
        if off < 0x10 or not 0 <= s <= 7:
            self.m.unmodelled("DMA2", off, size, value)
            return
        if reg == 0x0:
            was = self.scr[s] & 1
            if s == self.S:
                if was and not value & 1:
                    self.sndtr[s] = self.remaining(t)
                    self.stop(t)
                    self.scr[s] = value & 0x0FEFFFFE
                elif not was and value & 1:
                    self.scr[s] = value & 0x0FEFFFFF
                    if self.flags:
                        self.m.log("DMA2 stream 7 enabled with its flags set: RM0090 10.3.17 forbids it")
                    if (value >> 6) & 3 != 1 or (value >> 25) & 7 != 4:
                        self.m.log("DMA2 stream 7: only memory-to-peripheral on channel 4 (USART1_TX) is modelled")
                    else:
                        self._start(self.sm0ar[s], self.spar[s], self.sndtr[s], t)
                else:
                    self.scr[s] = value & 0x0FEFFFFF if not was else (self.scr[s] & 1) | (value & 0x0FEFFFFE)
                self._irq_check()
            elif s in self.SPI_S:
                was = self.scr[s] & 1
                self.scr[s] = value & 0x0FEFFFFF
                if was and not value & 1:
                    self.spi_abort(t)
                elif not was and value & 1:
                    if self.spi_flags[self.SPI_S.index(s)]:
                        self.m.log(f"DMA2 stream {s} enabled with its flags set: RM0090 10.3.17 forbids it")
                    self.spi_try_start(t)
            else:
                self.scr[s] = value & 0x0FEFFFFF
        elif not self.scr[s] & 1:
            if reg == 0x4:
                self.sndtr[s] = value & 0xFFFF
            elif reg == 0x8:
                self.spar[s] = value
            elif reg == 0xC:
                self.sm0ar[s] = value
            elif reg == 0x10:
                self.sm1ar[s] = value
            elif reg == 0x14:
                self.sfcr[s] = (value & 0x87) | (self.sfcr[s] & 0x38)   # FS (5:3) is read-only
