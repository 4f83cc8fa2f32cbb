"""SPI1 in master mode (RM0008 25.5 / RM0090 28.5: CR1, CR2, SR, DR, CRCPR, RXCRCR, TXCRCR,
I2SCFGR, I2SPR), 8-bit frames, full duplex, and the sensors on its bus.

Timing: a frame takes 8 SCK periods, f_SCK = f_PCLK2 / 2^(BR+1) as the image configured.
A DR write while the shift register is idle starts a frame at once (TXE stays set, BSY is
set); RXNE is set when the frame has been clocked, and the received byte is in DR; a frame
completing while RXNE is still set sets OVR (the byte is lost). Polling SR while a frame is
in flight fast-forwards device time to its end (the core would only have spun): that time
is accounted as busy-wait.

DMA (CR2 RXDMAEN | TXDMAEN with the DMA channels of dma.py enabled): the DMA feeds DR and
takes the received bytes; dma_exchange clocks the whole transfer through the same models,
one frame time per byte, and BSY reads 1 until its last frame has been clocked.

The sensors: the chip-select GPIO lines (targets.py wiring) select the ADXL355 or one of the
three ADXRS450; the bytes go to the SAME C models imubench-sim links (libimumodels.so,
sim_spi_exchange with the injected bus faults). A transaction is committed to the model once,
when its chip select rises, with the bytes the firmware really clocked; while it is in
progress each reply byte is obtained by running the transaction so far on a copy of the
model's state (simlib_spi_peek), so the model's state changes exactly once per transaction.
With no chip select low MISO reads 0x00 (the boards pull it down). CPOL/CPHA, bit order and
16-bit frames are not checked against the parts (the images use mode 0, 8 bit, MSB first).
"""
from __future__ import annotations

import ctypes

SR_RXNE, SR_TXE, SR_MODF, SR_OVR, SR_BSY = 1 << 0, 1 << 1, 1 << 5, 1 << 6, 1 << 7
CR1_MSTR, CR1_SPE = 1 << 2, 1 << 6


class Spi:
    def __init__(self, machine, lib):
        self.m = machine
        self.lib = lib
        self.reset()
        self.transactions = 0
        self.bytes = 0
        self.mismatches = 0
        self.bus_time = 0.0        # device seconds SCK ran (statistics)

    def reset(self) -> None:
        self.cr1 = 0
        self.cr2 = 0
        self.crcpr = 7
        self.i2spr = 0x0002          # RM0008 25.5.9 / RM0090 28.5.9: I2SDIV = 2
        self.rxne = False
        self.ovr = False
        self.dr_rx = 0
        self.busy_until = -1.0     # end of the frame in flight
        self.frame_rx = None       # byte the frame in flight will receive
        self.cs: int | None = None
        self.tx = bytearray()
        self.rx = bytearray()
        self.t_cs = 0.0
        self.dma_busy_until = -1.0
        self.control_during_transaction = False

    def frame_time(self) -> float:
        br = (self.cr1 >> 3) & 7
        return 8.0 * (2 ** (br + 1)) / self.m.rcc.pclk2_hz()

    # ------------------------------------------------------------ time
    def update(self, t: float) -> None:
        if self.frame_rx is not None and t >= self.busy_until:
            if self.rxne:
                self.ovr = True
            else:
                self.dr_rx = self.frame_rx
                self.rxne = True
            self.frame_rx = None


    # ------------------------------------------------------ chip selects
    def select(self, cs: int | None, t: float) -> None:
        """The wiring saw the chip selects change: cs = the one low, None = none."""
        if self.cs is not None and cs != self.cs:
            self._commit()
        if cs is not None and cs != self.cs:
            self.cs = cs
            self.tx = bytearray()
            self.rx = bytearray()
            self.t_cs = t
            self.control_during_transaction = False
        self.cs = cs

    def _commit(self) -> None:
        if not self.tx:
            return
        n = len(self.tx)
        out = (ctypes.c_uint8 * n)()
        self.m.set_model_time(self.t_cs)
        self.lib.simlib_spi_commit(self.cs, bytes(self.tx), out, n)
        self.transactions += 1
        if bytes(out) != bytes(self.rx[:n]):
            if self.control_during_transaction:
                # the control channel changed the sensor (a fault injected) between the bytes
                # the image received and this commit: the harness's doing, not the image's
                self.m.log(f"SPI: cs {self.cs} reply changed by the control channel during the transaction "
                           f"({bytes(self.rx[:n]).hex()} vs {bytes(out).hex()})")
            else:
                self.mismatches += 1
                self.m.log(f"SPI: cs {self.cs} reply differs from the bytes clocked "
                           f"({bytes(self.rx[:n]).hex()} vs {bytes(out).hex()})")
        self.tx = bytearray()
        self.rx = bytearray()
        self.control_during_transaction = False

    def _peek(self) -> int:
        n = len(self.tx)
        tx = bytes(self.tx)
        if self.cs != 0 and n < 4:
            tx = tx + bytes(4 - n)  # the gyros answer whole 32-bit frames
        out = (ctypes.c_uint8 * len(tx))()
        self.m.set_model_time(self.t_cs)
        self.lib.simlib_spi_peek(self.cs, tx, out, len(tx))
        return out[n - 1]

    def dma_exchange(self, data: bytes, t: float) -> float:
        """A DMA transfer of `data` starting at t: the bytes join the transaction in progress;
        returns the device time its last frame ends (dma_received then gives the reply)."""
        if not (self.cr1 & CR1_SPE and self.cr1 & CR1_MSTR):
            self.m.log("SPI1: DMA requests while the SPI is not an enabled master: nothing clocked")
        n = len(data)
        start = max(t, self.busy_until if self.frame_rx is not None else t, self.dma_busy_until)
        if self.cs is not None:
            self.tx += data
        dt = self.frame_time() * n
        self.bytes += n
        self.bus_time += dt
        self.dma_busy_until = start + dt
        return start + dt

    def dma_received(self, n: int) -> bytes:
        """The bytes the last n clocked brought back, asked for when they have been clocked
        (the end of the DMA transfer): as late as the polled path asks, so a change made
        through the control channel while the transfer ran (a fault) is in both this reply
        and the transaction committed at chip select rise."""
        if self.cs is None:
            return bytes(n)
        tx = bytes(self.tx)
        if self.cs != 0 and len(tx) < 4:
            tx = tx + bytes(4 - len(tx))
        out = (ctypes.c_uint8 * len(tx))()
        self.m.set_model_time(self.t_cs)
        self.lib.simlib_spi_peek(self.cs, tx, out, len(tx))
        got = bytes(out)[len(self.tx) - n:len(self.tx)]
        self.rx += got
        return got

    # ------------------------------------------------------------ registers
    def read(self, off: int, size: int, t: float) -> int:
        if off == 0x8:
            if self.frame_rx is not None and t < self.busy_until:
                self.m.busy_wait_until(self.busy_until)   # polling a frame in flight
                t = self.m.now()
            self.update(t)
            sr = SR_TXE
            if self.rxne:
                sr |= SR_RXNE
            if self.ovr:
                sr |= SR_OVR
            if self.frame_rx is not None or t < self.dma_busy_until:
                sr |= SR_BSY
            return sr
        self.update(t)
        if off == 0xC:
            v = self.dr_rx
            self.rxne = False
            return v
        if off == 0x0:
            return self.cr1
        if off == 0x4:
            return self.cr2
        if off == 0x10:
            return self.crcpr
        if off == 0x20:
            return self.i2spr
        if off in (0x14, 0x18, 0x1C):
            return 0
        self.m.unmodelled("SPI1", off, size, None)
        return 0

    def write(self, off: int, size: int, value: int, t: float) -> None:
        self.update(t)
        if off == 0x0:
            self.cr1 = value & 0xFFFF
            if self.cr1 & CR1_SPE and not self.cr1 & (1 << 9):
                self.m.log("SPI1: hardware NSS (SSM = 0) is not modelled")
        elif off == 0x4:
            self.cr2 = value & (0xF7 if self.m.target.name == "f4" else 0xE7)   # FRF (bit 4): F4 only
            if self.cr2 & 3:
                self.m.dma.spi_try_start(t)
        elif off == 0xC:
            if not (self.cr1 & CR1_SPE and self.cr1 & CR1_MSTR):
                self.m.log("SPI1: DR written while the SPI is not an enabled master: ignored")
                return
            if self.frame_rx is not None:
                # the firmware waits for RXNE before the next byte; a back-to-back write
                # would queue behind the frame in flight
                self.m.busy_wait_until(self.busy_until)
                t = self.m.now()
                self.update(t)
            byte = value & 0xFF
            if self.cs is not None:
                self.tx.append(byte)
                rx = self._peek()
                self.rx.append(rx)
            else:
                rx = 0x00
            dt = self.frame_time()
            self.busy_until = t + dt
            self.frame_rx = rx
            self.bytes += 1
            self.bus_time += dt
            # not an event: the frame's end is seen when SR or DR is read (nothing else
            # looks at it; the images use no SPI interrupt)
        elif off == 0x10:
            self.crcpr = value & 0xFFFF
        elif off == 0x20:
            self.i2spr = value & 0x3FF
        elif off == 0x8:
            if not value & (1 << 4):
                pass  # CRCERR write-0-to-clear: no CRC modelled
        else:
            self.m.unmodelled("SPI1", off, size, value)
