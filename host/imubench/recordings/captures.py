"""Reading our own files (imubench.recordings.read, formats ``npz`` and ``capture``): the
``imubench decode --npz`` arrays, read member by member after their headers are checked, and a
session's capture-N.bin, decoded frame by frame into arrays that grow by blocks."""
from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from imubench import memory
from imubench.files import FileRefused, MiB, open_input
from imubench.recordings import Recording, RecordingError, from_arrays
from imubench.recordings.progress import progress

#: what the arrays of one .npz member may take once read (checked from its header before reading)
MAX_NPZ_MEMBER_BYTES = 1024 * MiB
def _check_npz(path: Path) -> None:
    """Refuse a .npz whose members would take more than MAX_NPZ_MEMBER_BYTES once read, or
    that are not what their header says: each member's .npy header (shape, dtype) is read
    before numpy allocates anything (a 10 MB file may claim gigabytes)."""
    fmt = np.lib.format
    try:
        with open_input(path) as fh, zipfile.ZipFile(fh) as zf:
            for info in zf.infolist():
                if not info.filename.endswith(".npy"):
                    continue
                with zf.open(info) as m:
                    version = fmt.read_magic(m)
                    shape, _fortran, dtype = (fmt.read_array_header_1_0 if version == (1, 0)
                                              else fmt.read_array_header_2_0)(m, max_header_size=10000)
                    if dtype.hasobject:
                        raise RecordingError(f"{path}: member {info.filename} holds Python objects; "
                                             "imubench's npz holds numbers only")
                    nbytes = int(np.prod(shape, dtype=object)) * dtype.itemsize
                    if nbytes > MAX_NPZ_MEMBER_BYTES:
                        raise RecordingError(f"{path}: member {info.filename} declares {nbytes / MiB:.0f} MiB "
                                             f"(shape {shape}), more than the limit of "
                                             f"{MAX_NPZ_MEMBER_BYTES / MiB:.0f} MiB")
                    if nbytes > info.file_size:
                        raise RecordingError(f"{path}: member {info.filename} declares {nbytes} bytes of data but "
                                             f"holds {info.file_size}: damaged")
    except FileRefused as e:
        raise RecordingError(str(e)) from None
    except RecordingError:
        raise
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as e:
        raise RecordingError(f"{path}: not a .npz file ({e})") from None


def _npz_members(path: Path) -> dict:
    """{name: (member, shape, dtype, fortran)} of a .npz's .npy members, from their headers."""
    fmt = np.lib.format
    out = {}
    with open_input(path) as fh, zipfile.ZipFile(fh) as zf:
        for info in zf.infolist():
            if info.filename.endswith(".npy"):
                with zf.open(info) as m:
                    version = fmt.read_magic(m)
                    shape, fortran, dtype = (fmt.read_array_header_1_0 if version == (1, 0)
                                             else fmt.read_array_header_2_0)(m, max_header_size=10000)
                out[info.filename[:-4]] = (info.filename, shape, dtype, fortran)
    return out


def _npz_blocks(path: Path, member, step: int = 1 << 20):
    """(start, rows) of a .npz member (C order) a block of `step` rows at a time, read from the zip
    stream: the member is never held whole."""
    fmt = np.lib.format
    name, shape, dtype, _ = member
    row = int(np.prod(shape[1:], dtype=np.int64)) if len(shape) > 1 else 1
    with open_input(path) as fh, zipfile.ZipFile(fh) as zf, zf.open(name) as m:
        version = fmt.read_magic(m)
        (fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0)(m, max_header_size=10000)
        n = shape[0] if shape else 1
        for i in range(0, n, step):
            k = min(step, n - i)
            buf = m.read(k * row * dtype.itemsize)
            if len(buf) != k * row * dtype.itemsize:
                raise RecordingError(f"{path}: member {name} ends early: damaged")
            yield i, np.frombuffer(buf, dtype=dtype).reshape((k,) + tuple(shape[1:]))


def read_npz(path: Path, **opt) -> Recording:
    _check_npz(path)
    try:
        members = _npz_members(path)
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as e:
        raise RecordingError(f"{path}: not a .npz file ({e})") from None
    need = ("accel_mps2", "rate_rad_s")
    if not all(k in members for k in need):
        raise RecordingError(f"{path.name} holds {', '.join(members)}; imubench's npz (imubench decode --npz) "
                             f"has {', '.join(need)} and t_us")
    n = members["accel_mps2"][1][0] if members["accel_mps2"][1] else 0
    for k in ("accel_mps2", "rate_rad_s", "t_us", "sample_index", "status"):
        if k in members and (members[k][3] or not members[k][1] or members[k][1][0] != n):
            raise RecordingError(f"{path}: member {k} has shape {members[k][1]} (Fortran order: {members[k][3]}); "
                                 f"expected {n} rows in C order as imubench decode --npz writes them")
    budget = opt.get("memory_budget")
    limit = memory.sample_limit(budget, 6, "t_us" in members)
    if n > limit:
        raise RecordingError(f"{path}: {n:,} samples, more than the limit of {limit:,} of the memory budget of "
                             f"{memory.budget_text(budget)}; give a larger --memory-budget")
    dtype = memory.storage_dtype(n, budget, 6, "t_us" in members) or np.float32
    arrays = {}
    try:
        for k in need:
            out = np.empty(members[k][1], dtype=dtype)
            for i, blk in _npz_blocks(path, members[k]):
                out[i:i + len(blk)] = blk
            arrays[k] = out
        t = None
        if "t_us" in members:
            t = np.empty(n)
            for i, blk in _npz_blocks(path, members["t_us"]):
                np.multiply(blk, 1e-6, out=t[i:i + len(blk)])
        breaks, notes = [], []
        if "sample_index" in members:
            last = None
            for i, blk in _npz_blocks(path, members["sample_index"]):
                si = np.asarray(blk, np.int64)
                if last is not None:
                    si = np.concatenate([[last], si])
                    i -= 1
                for k in np.flatnonzero(np.diff(si) > 1):
                    breaks.append((int(i + k + 1), f"{int(si[k + 1] - si[k] - 1)} samples lost on the link before "
                                                   f"sample {i + k + 1}"))
                last = int(si[-1]) if len(si) else last
        if "status" in members:
            bad = sum(int(np.count_nonzero(blk)) for _, blk in _npz_blocks(path, members["status"]))
            if bad:
                notes.append(f"{bad} samples flagged bad by the device (status bits)")
    except RecordingError:
        raise
    except (zipfile.BadZipFile, ValueError, OSError, EOFError, TypeError) as e:
        raise RecordingError(f"{path}: not a .npz file ({e})") from None
    rec = from_arrays(arrays["accel_mps2"], arrays["rate_rad_s"], t_s=t, rate_hz=opt.get("rate_hz"), source=str(path),
                      fmt="npz", notes=notes, device=opt.get("device"), copy=False)
    rec.breaks = sorted(rec.breaks + [b for b in breaks if b[0] not in {x[0] for x in rec.breaks}])
    return rec


class _Growing:
    """Samples appended block by block into arrays allocated once from an estimate of the count (grown
    by half when it was short), values float64 or float32 as the budget holds them, the sample limit
    checked at every allocation."""

    def __init__(self, path: Path, budget: int | None):
        self.path, self.budget, self.n = path, budget, 0
        self.acc = self.gyr = self.t_us = self.index = None

    def _alloc(self, rows: int) -> None:
        limit = memory.sample_limit(self.budget, 6, True)
        if rows > limit:
            raise RecordingError(f"{self.path}: about {rows:,} samples, more than the limit of {limit:,} of the memory "
                                 f"budget of {memory.budget_text(self.budget)}; give a larger "
                                 "--memory-budget, or cut the capture")
        dtype = self.acc.dtype if self.acc is not None else (memory.storage_dtype(rows, self.budget, 6, True)
                                                            or np.float32)
        new = [np.empty((rows, 3), dtype), np.empty((rows, 3), dtype), np.empty(rows, np.int64), np.empty(rows, np.int64)]
        if self.acc is not None:
            for dst, src in zip(new, (self.acc, self.gyr, self.t_us, self.index)):
                dst[:self.n] = src[:self.n]
        self.acc, self.gyr, self.t_us, self.index = new

    def append(self, block, estimate: int) -> None:
        m = len(block)
        if self.acc is None:
            self._alloc(max(estimate, m))
        elif self.n + m > len(self.acc):
            self._alloc(max(self.n + m, int(len(self.acc) * 1.5)))
        acc, gyr = block.si()
        sl = slice(self.n, self.n + m)
        self.acc[sl], self.gyr[sl], self.t_us[sl], self.index[sl] = acc, gyr, block.t_us, block.sample_index
        self.n += m


def read_capture(path: Path, **opt) -> Recording:
    """A session's capture-N.bin, fed to the stream decoder a megabyte at a time; the samples of each
    megabyte converted (nominal scaling) into arrays sized from the file's length: the file and the
    decoded frames are never held whole."""
    from imubench.wire.decoder import StreamDecoder
    size = path.stat().st_size
    dec = StreamDecoder()
    got = {False: _Growing(path, opt.get("memory_budget")), True: _Growing(path, opt.get("memory_budget"))}
    step, done = 1 << 20, 0
    bar = progress(size, f"reading {path.name}") if size > (8 << 20) else None
    try:
        with open_input(path) as f:
            while True:
                data = f.read(step)
                if not data:
                    break
                done += len(data)
                dec.feed(data)
                for cal in (False, True):
                    b = dec.take_samples(cal)
                    if b is not None and len(b):
                        got[cal].append(b, int((got[cal].n + len(b)) * size / done * 1.02) + 16)
                if bar is not None:
                    bar.update(len(data))
    except FileRefused as e:
        raise RecordingError(str(e)) from None
    finally:
        if bar is not None:
            bar.close()
    st = dec.stats
    g = got[False] if got[False].n else got[True]
    if g.n < 3:
        raise RecordingError(f"{path.name}: no samples decoded (frames ok {st.frames_ok}, rejected "
                             f"{st.frames_rejected}); is it a capture-N.bin of an imubench session?")
    n = g.n
    notes = [f"{'raw' if g is got[False] else 'calibrated'} samples of an imubench device, nominal scaling"]
    breaks = []
    si = g.index[:n]
    for k in np.flatnonzero(np.diff(si) > 1):
        breaks.append((int(k + 1), f"{int(si[k + 1] - si[k] - 1)} samples lost on the link before sample {k + 1}"))
    t = g.t_us[:n].astype(np.float64)
    t *= 1e-6
    g.t_us = g.index = None
    rec = from_arrays(g.acc[:n], g.gyr[:n], t_s=t, source=str(path), fmt="capture", notes=notes,
                      device=opt.get("device"), copy=False)
    rec.breaks = sorted(rec.breaks + [b for b in breaks if b[0] not in {x[0] for x in rec.breaks}])
    return rec
