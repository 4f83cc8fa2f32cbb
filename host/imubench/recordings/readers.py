"""The file formats a recording is read from (imubench.recordings.read):

- ``csv``: any CSV (comma, semicolon, tab or space separated). With a header row, columns are
  mapped by name (``columns`` = {"ax": name,
  ..., "gz": name, "t": name}, from ``--columns`` or a profile file), else found among common
  names (acc_x/ax/accel_x..., gyr_x/gx/gyro_x..., t/time/timestamp) and said so. Time from the
  column (its unit declared, or in its name: t_s, t_ms, t_us, t_ns) or from ``rate_hz``. Units
  declared, or in the column names as our own CSV writes them (ax_mps2, wx_rad_s). Without a
  header (the first line is numbers, e.g. mikoff/imu-calib's logs) columns are taken by position:
  six columns are ``ax ay az gx gy gz``, seven ``t ax ay az gx gy gz`` (said in a note), or
  ``columns`` maps keys to 1-based positions (``ax=2,...``).
- ``imutk``: imu_tk's ASCII files, one per sensor, each line "t x y z" (t in seconds): the
  accelerometer file and ``gyro_file``.
- ``imucal``: imucal's CSV layouts: a session (``n_samples,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z``)
  or an annotated, cut session (``part,samples,acc_x,...,gyr_z``: every change of part is a
  cut, recorded as a break; the parts are kept as an annotation). No time: ``rate_hz``.
- ``npz``: ``imubench decode --npz`` output (t_us, sample_index, accel_mps2, rate_rad_s).
- ``capture``: a calibration session's capture-N.bin (the device's raw frames).
- ``rosbag``: ROS 1 (.bag) or ROS 2 (directory with metadata.yaml, .db3, .mcap) bags with
  sensor_msgs/Imu messages (m/s², rad/s by the message's definition), read with the optional
  ``rosbags`` library (pip install 'imubench[rosbag]').
"""
from __future__ import annotations

import csv
import gzip
import io
import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from imubench.files import (
    MAX_JSON_BYTES,
    MAX_LINE_CHARS,
    FileRefused,
    bounded_lines,
    open_input,
    read_text,
)
from imubench import memory
from imubench.recordings import FORMATS, Recording, RecordingError, from_arrays
from imubench.recordings.bags import read_rosbag
from imubench.recordings.captures import read_capture, read_npz
from imubench.recordings.progress import progress

#: the most samples a recording may hold under the default memory budget (imubench.memory.sample_limit:
#: 24 h at 200 Hz is a normal input); --memory-budget sets another
MAX_SAMPLES = memory.sample_limit()
#: a value of an accelerometer or gyro beyond this in any unit (m/s², g, mg, rad/s, °/s, counts of a
#: 32-bit register) is no sensor's reading: the line is named and the file refused
ABSURD = 1e12
#: the lines parsed at a time: text is never held whole, only this many lines of it
CHUNK_LINES = 65536

KEYS = ("ax", "ay", "az", "gx", "gy", "gz")
_CANDIDATES = {
    "accel": [("acc_x", "acc_y", "acc_z"), ("ax", "ay", "az"), ("accel_x", "accel_y", "accel_z"),
              ("accx", "accy", "accz"), ("ax_mps2", "ay_mps2", "az_mps2"), ("ax_g", "ay_g", "az_g"),
              ("linear_acceleration_x", "linear_acceleration_y", "linear_acceleration_z"),
              ("accelx", "accely", "accelz"), ("a_x", "a_y", "a_z"), ("tx", "ty", "tz")],
    "gyro": [("gyr_x", "gyr_y", "gyr_z"), ("gx", "gy", "gz"), ("gyro_x", "gyro_y", "gyro_z"),
             ("gyrx", "gyry", "gyrz"), ("wx_rad_s", "wy_rad_s", "wz_rad_s"), ("wx", "wy", "wz"),
             ("angular_velocity_x", "angular_velocity_y", "angular_velocity_z")],
    "t": ["t", "time", "timestamp", "t_s", "time_s", "t_ms", "time_ms", "t_us", "time_us", "t_ns", "time_ns"],
}
_TIME_SUFFIX = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}
_UNIT_SUFFIX_ACC = {"mps2": "mps2", "g": "g", "mg": "mg"}
_UNIT_SUFFIX_GYR = {"rad_s": "rad_s", "dps": "dps"}


def _open_text(path: Path):
    """A text file (gzip-compressed by its suffix), refused unless it is a regular file."""
    if path.suffix == ".gz":
        raw = open_input(path)
        g = gzip.GzipFile(fileobj=raw, mode="rb")
        g.myfileobj = raw           # GzipFile closes the file it holds there (as when it opened it)
        return io.TextIOWrapper(g, newline="")
    return open_input(path, binary=False, newline="")


def _lines(f, path: Path):
    """The lines of f, each bounded (files.bounded_lines); a refusal or a damaged gzip stream
    is a RecordingError."""
    try:
        yield from bounded_lines(f, MAX_LINE_CHARS, str(path))
    except FileRefused as e:
        raise RecordingError(str(e)) from None
    except (OSError, EOFError, UnicodeDecodeError) as e:
        raise RecordingError(f"{path}: unreadable ({type(e).__name__}: {e})") from None


#: lines looked at to find a text table's layout (preamble, header, delimiter)
SNIFF_LINES = 400
#: delimiters tried, in this order on a tie; None: runs of whitespace (spaces, tabs, at line ends too)
_DELIMS = (",", ";", "\t", None)
_COMMENT = ("#", "%")
#: a preamble line's key that states the sample rate in Hz (compared lower-case, letters only)
_RATE_KEYS = {"fs", "fshz", "samplerate", "sampleratehz", "samplingrate", "samplingratehz", "samplingfrequency",
              "samplingfrequencyhz", "samplefrequency", "frequency", "frequencyhz", "rate", "ratehz", "datarate",
              "odr", "odrhz", "outputdatarate", "samplespersecond", "sps"}


@dataclass
class Layout:
    """Where a text table's numbers are: its delimiter (None: whitespace), columns, the line
    (0-based) of its first data row, its header (a row, or a # comment line, or none) and the
    lines before it (the preamble, metadata such as ``Fs,100``)."""
    delim: str | None
    ncols: int
    start: int
    header: list[str] | None = None
    header_line: int | None = None
    header_commented: bool = False
    preamble: list[tuple[int, str]] = field(default_factory=list)
    skip_rows: int = 0

    def describe(self) -> str | None:
        """One line on what was found before the data, or None when it is a plain table."""
        if not self.preamble and not self.header_commented:
            return None
        where = f"line {self.header_line + 1}" if self.header is not None else f"line {self.start + 1}"
        what = ("columns named by the comment line" if self.header_commented else
                "header row" if self.header is not None else "data")
        pre = ""
        if self.preamble:
            shown = ", ".join(repr(t[:30]) for _, t in self.preamble[:3]) + (", ..." if len(self.preamble) > 3 else "")
            pre = f" after {len(self.preamble)} line(s) of preamble ({shown}), read as metadata"
        return f"{what} at {where}{pre} (--skip-rows N to start elsewhere)"


def _fields(line: str, delim: str | None) -> list[str]:
    """The fields of a line: whitespace at its ends and a trailing delimiter are format, not fields."""
    s = line.strip()
    if delim is None:
        return s.split()
    f = [c.strip() for c in s.split(delim)]
    return f[:-1] if len(f) > 1 and f[-1] == "" else f


def _is_comment(line: str) -> bool:
    return line.lstrip().startswith(_COMMENT)


def _is_number(c: str) -> bool:
    try:
        float(c)
    except ValueError:
        return False
    return True


def _numeric(cols: list[str]) -> bool:
    """True when every field of a line is a number (a headerless table)."""
    return bool(cols) and all(map(_is_number, cols))


def _datarow(cols: list[str]) -> bool:
    """A row of samples: three numbers or more, and at most a quarter of its fields not numbers
    (a label such as imucal's part name)."""
    n = sum(map(_is_number, cols))
    return n >= 3 and n >= 0.75 * len(cols)


def _layout(path: Path, skip_rows: int | None = None) -> Layout:
    """The layout of a text table, from its first lines: the delimiter under which the most lines
    are rows of numbers of one width; the data from the first of 5 such rows in a row; the
    header the line before (a row of that width with names, or a # comment line that splits
    into that many names); the lines above it the preamble. skip_rows: lines skipped first."""
    skip = int(skip_rows or 0)
    lines = []
    with _open_text(path) as f:
        for i, line in enumerate(_lines(f, path)):
            if i >= skip + SNIFF_LINES:
                break
            lines.append(line)
    body = [(i, ln) for i, ln in enumerate(lines) if i >= skip and ln.strip()]
    if not body:
        raise RecordingError(f"{path} is empty" + (f" after the {skip} rows skipped" if skip else ""))
    rows = [(i, ln) for i, ln in body if not _is_comment(ln)]
    best = None
    for delim in _DELIMS:
        widths = [len(f) for f in (_fields(ln, delim) for _, ln in rows) if _datarow(f)]
        if not widths:
            continue
        width = max(set(widths), key=lambda w: (widths.count(w), w))
        score = (widths.count(width), width)
        if best is None or score > best[0]:
            best = (score, delim, width)
    if best is None:
        if any(re.search(r"\d,\d", ln) and ";" in ln for _, ln in rows):
            raise RecordingError(f"{path.name}: its numbers have decimal commas (1,5 for 1.5), which are not "
                                 "read: export the file with decimal points")
        raise RecordingError(f"{path.name}: no rows of numbers in its first {len(lines)} lines"
                             + (f" after the {skip} rows skipped" if skip else "")
                             + "; is it a table of samples? (--skip-rows N starts at line N + 1)")
    _, delim, width = best
    ok = [len(f) == width and _datarow(f) for f in (_fields(ln, delim) for _, ln in rows)]
    run = 5
    start_k = next((k for k in range(len(rows)) if all(ok[k:k + run])), None)
    if start_k is None:
        raise RecordingError(f"{path.name}: no {run} rows of {width} numbers in a row in its first {len(lines)} lines; "
                             "check the file, or start it with --skip-rows N")
    start = rows[start_k][0]
    lay = Layout(delim=delim, ncols=width, start=start, skip_rows=skip)
    before = [(i, ln) for i, ln in body if i < start]
    # the header: the row just before the data, or the nearest of the comment lines just before it
    k = len(before) - 1
    if k >= 0 and not _is_comment(before[k][1]):
        f = _fields(before[k][1], delim)
        if len(f) == width and not _datarow(f):
            lay.header, lay.header_line = f, before[k][0]
    else:
        while k >= 0 and _is_comment(before[k][1]):
            text = before[k][1].strip().lstrip("#%").strip()
            for d in dict.fromkeys((delim, None)):
                f = _fields(text, d)
                if len(f) == width and not _datarow(f):
                    lay.header, lay.header_line, lay.header_commented = f, before[k][0], True
                    break
            if lay.header is not None:
                break
            k -= 1
    top = lay.header_line if lay.header is not None else start
    lay.preamble = [(i, ln.strip()) for i, ln in before if i < top and not (lay.header_commented and _is_comment(ln))]
    return lay


def _preamble_rate(lay: Layout) -> tuple[float, str] | None:
    """The sample rate a preamble states (a line such as ``Fs,100`` or ``Sample rate: 200 Hz``), with
    the line; None when it states none, or several different ones."""
    found = {}
    for _, text in lay.preamble:
        m = re.match(r"^[#%\s]*([A-Za-z][A-Za-z _()/.-]*?)\s*(?:\(hz\)|\[hz\])?\s*[,;:=\t ]\s*"
                     r"([0-9]+(?:\.[0-9]*)?(?:[eE][+-]?[0-9]+)?)\s*(hz)?\s*[,;]*\s*$", text, re.IGNORECASE)
        if not m:
            continue
        key = re.sub(r"[^a-z]", "", m.group(1).lower())
        if key in _RATE_KEYS and float(m.group(2)) > 0:
            found.setdefault(float(m.group(2)), text)
    if len(found) != 1:
        return None
    (rate, text), = found.items()
    return rate, text


def _position(f) -> int:
    """The bytes of the file on disk consumed so far (of the compressed file for .gz)."""
    try:
        return os.lseek(f.fileno(), 0, os.SEEK_CUR)
    except (OSError, ValueError, AttributeError):
        return 0


def _count_lines(path: Path, stop: int) -> int:
    """The lines of a text file (of its decompressed text for .gz), counted in binary blocks without
    holding them; counting stops past `stop` (a gzip bomb is not decompressed to its end)."""
    n, last = 0, b"\n"
    try:
        with (_open_binary(path)) as f:
            while n <= stop:
                blk = f.read(1 << 22)
                if not blk:
                    break
                n += blk.count(b"\n")
                last = blk[-1:]
    except (OSError, EOFError) as e:
        raise RecordingError(f"{path}: unreadable ({type(e).__name__}: {e})") from None
    return n + (last != b"\n")


def _open_binary(path: Path):
    if path.suffix == ".gz":
        raw = open_input(path)
        g = gzip.GzipFile(fileobj=raw, mode="rb")
        g.myfileobj = raw
        return g
    return open_input(path)


#: characters of text read at a time (split into lines by str.split: no Python work per line)
BLOCK_CHARS = 1 << 22
#: a blank line, or one of whitespace only, in a block with a newline added at both ends
_BLANK = re.compile(r"\n[ \t\r\f\v]*\n")


def _chunks(path: Path, start: int, progress=None):
    """(lines, numbers) of the data lines of a text file from its line start (0-based; blank lines and
    # or % comments skipped), about BLOCK_CHARS of text at a time, and their 1-based line numbers (a
    range when no line of the block was skipped, and then no line holds a comment): the file is
    streamed, never held whole, and split into lines by str.split, not line by line in Python. A line longer than MAX_LINE_CHARS is refused
    (a binary file). progress: a tqdm bar advanced by the bytes of the file consumed."""
    with _open_text(path) as f:
        it = _lines(f, path)
        for _ in range(start):
            if next(it, None) is None:
                return
        lineno, rest, done = start, "", 0
        try:
            while True:
                blk = f.read(BLOCK_CHARS)
                if not blk:
                    text = rest
                    rest = ""
                else:
                    text = rest + blk
                    cut = text.rfind("\n")
                    if cut < 0:
                        if len(text) > MAX_LINE_CHARS:
                            raise RecordingError(f"{path}: line {lineno + 1} is longer than the limit of "
                                                 f"{MAX_LINE_CHARS} characters; is it a text file of this format?")
                        rest = text
                        continue
                    text, rest = text[:cut], text[cut + 1:]
                if text:
                    lines = text.split("\n")
                    if max(map(len, lines)) > MAX_LINE_CHARS:
                        k = next(i for i, ln in enumerate(lines) if len(ln) > MAX_LINE_CHARS)
                        raise RecordingError(f"{path}: line {lineno + k + 1} is longer than the limit of "
                                             f"{MAX_LINE_CHARS} characters; is it a text file of this format?")
                    if "#" in text or "%" in text or _BLANK.search("\n" + text + "\n"):
                        keep = [(i, ln) for i, ln in enumerate(lines) if ln.strip() and not _is_comment(ln)]
                        chunk, numbers = [ln for _, ln in keep], [lineno + i + 1 for i, _ in keep]
                    else:
                        chunk, numbers = lines, range(lineno + 1, lineno + len(lines) + 1)
                    lineno += len(lines)
                    if chunk:
                        yield chunk, numbers
                if progress is not None:
                    pos = _position(f)
                    progress.update(max(0, pos - done))
                    done = max(done, pos)
                if not blk:
                    return
        except (OSError, EOFError, UnicodeDecodeError) as e:
            raise RecordingError(f"{path}: unreadable ({type(e).__name__}: {e})") from None


def _bad_row(what: str, path: Path, line: int, col: str, value: float) -> RecordingError:
    kind = "not a finite number" if not np.isfinite(value) else f"{value:.3g}, beyond any sensor's range (|x| > {ABSURD:.0e})"
    return RecordingError(f"{path.name}: line {line}, {col}: {kind}; fix or cut the file ({what})")


def _load_table(path: Path, delim: str | None, usecols: list[int], start: int, *, time_at: int | None = None,
                names: list[str] | None = None, budget: int | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """The numbers of the columns usecols of a text table from its line start, parsed CHUNK_LINES lines at
    a time into arrays allocated once: (values, t) with t the column at position time_at of usecols
    (float64 seconds or whatever unit the file has; None without) and values the others, as float64 when
    the memory budget holds them so, else float32 (imubench.memory). The lines are counted first, so the
    sample limit the budget sets is checked before anything is allocated. A value that is not finite or
    beyond any sensor's range (ABSURD) is refused with its line. names: the columns' names, for messages."""
    names = names or [f"column {c + 1}" for c in usecols]
    nval = len(usecols) - (time_at is not None)
    limit = memory.sample_limit(budget, nval, time_at is not None)
    lines = _count_lines(path, stop=start + limit + 1)
    rows = max(0, lines - start)
    dtype = memory.storage_dtype(rows, budget, nval, time_at is not None)
    if dtype is None:
        raise RecordingError(f"{path}: more than {limit:,} samples (counted {'over' if rows > limit else ''} "
                             f"{rows:,} lines), the limit of the memory budget of {memory.budget_text(budget)}; "
                             "give a larger --memory-budget, or cut the recording")
    vcols = [k for k in range(len(usecols)) if k != time_at]
    vals = np.empty((rows, nval), dtype=dtype)
    t = np.empty(rows, dtype=np.float64) if time_at is not None else None
    n = 0
    size = path.stat().st_size
    bar = progress(size, f"reading {path.name}") if size > (1 << 20) else None
    try:
        for chunk, numbers in _chunks(path, start, bar):
            try:                                   # comments: numpy's C parser only without any (see _chunks)
                a = np.loadtxt(chunk, delimiter=None if delim in (" ", "\t", None) else delim, usecols=usecols,
                               comments=None if isinstance(numbers, range) else _COMMENT, ndmin=2, dtype=np.float64)
            except ValueError as e:
                raise RecordingError(_not_numbers(path, chunk, numbers, delim, usecols, e, start)) from None
            if len(a) != len(chunk):
                raise RecordingError(f"{path}: {len(chunk)} lines gave {len(a)} rows; check the file")
            v = a[:, vcols]
            bad = ~np.isfinite(v) | (np.abs(v) > ABSURD)
            if time_at is not None:
                bad = np.column_stack([bad, ~np.isfinite(a[:, time_at])])
            if bad.any():
                r, c = np.argwhere(bad)[0]
                col = usecols[time_at] if c == nval else usecols[vcols[c]]
                value = a[r, time_at] if c == nval else v[r, c]
                raise _bad_row("first such value", path, numbers[r], names[usecols.index(col)], float(value))
            if n + len(a) > rows:
                raise RecordingError(f"{path} grew while it was read; read it when it is complete")
            vals[n:n + len(a)] = v
            if t is not None:
                t[n:n + len(a)] = a[:, time_at]
            n += len(a)
    finally:
        if bar is not None:
            bar.close()
    return vals[:n], (t[:n] if t is not None else None)


def _not_numbers(path: Path, chunk, numbers, delim, usecols, e, start) -> str:
    """The first line of a chunk that is not numbers, named (parsed again one line at a time: only
    after a failure)."""
    where = f"counted from line {start + 1}"
    for ln, no in zip(chunk, numbers):
        try:
            np.loadtxt([ln], delimiter=None if delim in (" ", "\t", None) else delim, usecols=usecols,
                       comments=_COMMENT, ndmin=2, dtype=np.float64)
        except ValueError as e1:
            e, where = e1, f"line {no}"
            break
    msg = re.sub(r" at row \d+", "", " ".join(str(e).split()))[:160]
    return (f"{path}: not numbers where numbers are expected ({msg}; {where}); "
            "check the delimiter and the header, or start at the header row with --skip-rows N (the lines before it)")


def _load(path: Path, delim: str | None, usecols: list[int], start: int, budget: int | None = None) -> np.ndarray:
    """All the columns usecols as one array (float64 or float32 by the budget): _load_table without a
    time column."""
    vals, _ = _load_table(path, delim, usecols, start, budget=budget)
    return vals


def detect_format(path, skip_rows: int | None = None) -> str:
    """The format of a file by its extension, else by its content (a header, the width of its rows);
    the choice is printed by the caller."""
    p = Path(path)
    if p.is_dir():
        if (p / "metadata.yaml").exists():
            return "rosbag"
        raise RecordingError(f"{p} is a directory but not a ROS 2 bag (no metadata.yaml); give a file")
    ext = "".join(p.suffixes[-2:]) if p.suffix == ".gz" else p.suffix
    ext = ext.lower()
    if ext in (".bag", ".db3", ".mcap"):
        return "rosbag"
    if ext == ".npz":
        return "npz"
    if ext == ".bin":
        return "capture"
    try:                    # by content: a text table
        lay = _layout(p, skip_rows)
    except RecordingError:
        if ext.startswith((".csv", ".txt")):
            raise
        lay = None
    except (UnicodeDecodeError, OSError):
        lay = None
    if lay is not None:
        low = [c.lower() for c in lay.header or []]
        if low[:1] == ["n_samples"] or low[:2] == ["part", "samples"]:
            return "imucal"
        if lay.header is None and lay.ncols == 4:
            return "imutk"
        return "csv"
    raise RecordingError(f"cannot tell the format of {p.name} from its name or its content: give --format "
                         f"({'|'.join(FORMATS)})")


def read(path, fmt: str | None = None, **opt) -> Recording:
    """Read a recording (fmt None: detect_format) with the options of the readers; the result's
    options are those that read it again the same way (declared and detected)."""
    p = Path(path)
    if not p.exists():
        raise RecordingError(f"{p}: no such file or directory; check the path")
    if not p.is_dir():
        _regular(p)                 # a FIFO or a device is refused before anything reads it
    declared = {k: v for k, v in opt.items() if v not in (None, {}, "")}
    detected = {}
    if not fmt:
        fmt = "imutk" if opt.get("gyro_file") else detect_format(p, opt.get("skip_rows"))
        detected["format"] = fmt
        ext = "".join(p.suffixes[-2:]).lower()
        if fmt == "imutk" or (fmt == "csv" and not ext.startswith((".csv", ".txt"))):
            why = "--gyro-file given" if opt.get("gyro_file") else "the file's content"
            detected_line = f"format {fmt} from {why} (--format {fmt})"
        else:
            detected_line = None
    else:
        detected_line = None
    if fmt not in FORMATS:
        raise RecordingError(f"unknown format {fmt!r}; one of {', '.join(FORMATS)}")
    sensor_notes = []
    if opt.get("sensor"):
        from imubench.recordings.sensors import default_units
        units = default_units(opt["sensor"], opt, sensor_notes)
        opt.update(units)
        detected.update(units)
    rec = {"csv": read_csv, "imutk": read_imutk, "imucal": read_imucal, "npz": read_npz,
           "capture": read_capture, "rosbag": read_rosbag}[fmt](p, **opt)
    if opt.get("sensor"):
        from imubench.recordings.sensors import apply_sensor
        apply_sensor(rec, opt["sensor"], opt.get("gyro_range_dps"))
    rec.detected = sensor_notes + rec.detected
    rec.options = {**declared, **detected, **rec.options}
    if detected_line:
        rec.detected.insert(0, detected_line)
    return rec


def _regular(path: Path) -> None:
    try:
        with open_input(path):
            pass
    except FileRefused as e:
        raise RecordingError(str(e)) from None


def _need_units(opt: dict, what: str) -> tuple[str, str]:
    au, gu = opt.get("accel_unit"), opt.get("gyro_unit")
    missing = [n for n, v in (("--accel-unit", au), ("--gyro-unit", gu)) if not v]
    if missing:
        raise RecordingError(f"{what} does not say its units: give {' and '.join(missing)} "
                             "(accelerometer mps2|g|mg|counts, gyro rad_s|dps|counts; for counts also "
                             "--accel-scale COUNTS_PER_G / --gyro-scale COUNTS_PER_DPS, or --sensor NAME)")
    return au, gu


def _common(opt: dict) -> dict:
    return {"accel_counts_per_g": opt.get("accel_counts_per_g"), "gyro_counts_per_dps": opt.get("gyro_counts_per_dps"),
            "device": opt.get("device"), "accel_offset": opt.get("accel_offset"),
            "gyro_offset": opt.get("gyro_offset")}


#: Unix time stamps of the years 2001 to 2100 in seconds: a time column in this range × 1000^k is in s, ms, us, ns
_EPOCH_S = (1.0e9, 4.1e9)


#: the sample rates an IMU log is taken to have when only its time steps tell the unit: the range is
#: narrower than the factor 1000 between units, so one unit at most puts the median step inside it
_RATE_RANGE_HZ = (10.0, 5000.0)


def _unit_from_steps(raw: np.ndarray, what: str, detected: list, options: dict) -> str | None:
    """The time unit in which the median step of relative time stamps is a sample period of
    10 Hz to 5 kHz (s, ms, us or ns differ by 1000, the range by 500: at most one fits); said
    in one line. None when no unit fits (the step is between the ranges, or not increasing)."""
    d = np.diff(raw[: min(len(raw), 100_001)])
    d = d[np.isfinite(d) & (d > 0)]
    if len(d) < max(2, len(raw) // 10):
        return None
    step = float(np.median(d))
    fits = [u for u, f in _TIME_SUFFIX.items() if _RATE_RANGE_HZ[0] <= 1.0 / (step * f) <= _RATE_RANGE_HZ[1]]
    if len(fits) != 1:
        return None
    u = fits[0]
    detected.append(f"time unit {u}: {what} steps by {step:.6g} (median), a {1.0 / (step * _TIME_SUFFIX[u]):.4g} Hz "
                    f"rate in {u}; no other unit gives an IMU's {_RATE_RANGE_HZ[0]:g}–{_RATE_RANGE_HZ[1]:g} Hz "
                    f"(--time-unit {u})")
    options["time_unit"] = u
    return u


def _time_seconds(raw: np.ndarray, unit: str | None, what: str, detected: list, options: dict) -> np.ndarray:
    """A time column in seconds: its unit declared, else settled when the values are Unix time
    stamps (their size says s, ms, us or ns) or when only one unit makes the median step an IMU's
    sample period (10 Hz to 5 kHz); each said in one line; else asked for."""
    if not unit and len(raw):
        mid = float(np.median(raw))
        for u, f in _TIME_SUFFIX.items():
            if _EPOCH_S[0] <= mid * f <= _EPOCH_S[1]:
                unit = u
                import datetime as _dt
                day = _dt.datetime.fromtimestamp(mid * f, _dt.timezone.utc).strftime("%Y-%m-%d")
                detected.append(f"time unit {u}: {what} holds Unix time stamps in {u} ({mid:.6g}, i.e. {day}) "
                                f"(--time-unit {u})")
                options["time_unit"] = u
                break
    if not unit and len(raw) > 2:
        unit = _unit_from_steps(raw, what, detected, options)
    if not unit:
        raise RecordingError(f"{what} does not say its unit: give --time-unit s|ms|us|ns "
                             "(or --rate HZ to ignore it)")
    if unit not in _TIME_SUFFIX:
        raise RecordingError(f"--time-unit {unit!r}: one of s, ms, us, ns")
    f = _TIME_SUFFIX[unit]
    if f != 1.0:
        np.multiply(raw, f, out=raw)            # in place: the reader's own array, no second copy
    return raw


def _layout_lines(lay: Layout, rate_hz: float | None, has_time: bool, detected: list, notes: list,
                  options: dict, mapped: bool = False) -> float | None:
    """What the layout settled, one line each (the preamble and header; a rate the preamble
    states), and the rate to use when the file has no time column. mapped: every column was
    named by an option (a commented header then settles nothing)."""
    d = lay.describe()
    if d:
        (notes if mapped and not lay.preamble else detected).append(d)
        if lay.preamble:
            options["skip_rows"] = lay.header_line if lay.header is not None else lay.start
    pre = _preamble_rate(lay)
    if pre is None:
        return rate_hz
    r, text = pre
    if has_time and not rate_hz:
        notes.append(f"the preamble states {text!r}; the file's time stamps are used")
    elif rate_hz and abs(rate_hz - r) > 1e-9 * r:
        notes.append(f"the preamble states {text!r}; --rate {rate_hz:g} is used")
    elif not rate_hz:
        detected.append(f"sample rate {r:g} Hz from the preamble line {text!r} (--rate {r:g})")
        options["rate_hz"] = r
        return r
    return rate_hz


# ------------------------------------------------------------------ csv
def read_csv(path: Path, *, columns: dict | None = None, time_column: str | None = None,
             time_unit: str | None = None, rate_hz: float | None = None, accel_unit: str | None = None,
             gyro_unit: str | None = None, skip_rows: int | None = None, **opt) -> Recording:
    lay = _layout(path, skip_rows)
    if lay.header is None:
        return _read_headerless(path, lay, columns=columns, time_unit=time_unit, rate_hz=rate_hz,
                                accel_unit=accel_unit, gyro_unit=gyro_unit, **opt)
    cols = lay.header
    low = {c.lower(): i for i, c in enumerate(cols)}
    notes, detected, options = [], [], {}
    mapping = dict(columns or {})
    if time_column:
        mapping["t"] = time_column
    unknown = [k for k in mapping if k not in (*KEYS, "t")]
    if unknown:
        raise RecordingError(f"--columns: unknown key(s) {', '.join(unknown)}; keys are ax ay az gx gy gz t")
    found_by_name = []
    for kind, keys in (("accel", KEYS[:3]), ("gyro", KEYS[3:])):
        if all(k in mapping for k in keys):
            continue
        if any(k in mapping for k in keys):
            raise RecordingError(f"--columns maps only some of {' '.join(keys)}: map all three")
        for cand in _CANDIDATES[kind]:
            if all(c in low for c in cand):
                mapping.update({k: cols[low[c]] for k, c in zip(keys, cand)})
                found_by_name.append(f"{kind} {', '.join(cols[low[c]] for c in cand)}")
                break
        else:
            raise RecordingError(f"{path.name}: no {kind} columns found among {', '.join(cols)}; map them with "
                                 f"--columns {'=NAME,'.join(keys)}=NAME (or a --profile file)")
    if "t" not in mapping and not rate_hz:
        for c in _CANDIDATES["t"]:
            if c in low:
                mapping["t"] = cols[low[c]]
                found_by_name.append(f"time {cols[low[c]]}")
                break
    missing = [v for v in mapping.values() if v.lower() not in low]
    if missing:
        raise RecordingError(f"{path.name} has no column {missing[0]!r}; its columns are {', '.join(cols)}")
    rate_hz = _layout_lines(lay, rate_hz, "t" in mapping, detected, notes, options, mapped=not found_by_name)
    if found_by_name:
        used = {mapping[k].lower() for k in mapping}
        ignored = [c for c in cols if c.lower() not in used]
        line = ("columns found by name: " + "; ".join(found_by_name)
                + (f"; not used: {', '.join(ignored)}" if ignored else "") + " (map others with --columns)")
        (detected if ignored or lay.header_commented else notes).append(line)
        options["columns"] = {k: v for k, v in mapping.items() if k != "t"}
        if "t" in mapping:
            options["time_column"] = mapping["t"]
    idx = [low[mapping[k].lower()] for k in KEYS]
    t_idx = low[mapping["t"].lower()] if "t" in mapping else None
    names = [mapping[k] for k in KEYS] + ([mapping["t"]] if t_idx is not None else [])
    data, t_raw = _load_table(path, lay.delim, idx + ([t_idx] if t_idx is not None else []), lay.start,
                              time_at=6 if t_idx is not None else None, names=names, budget=opt.get("memory_budget"))
    # units: declared, or declared by the column names
    if not accel_unit:
        suf = mapping["ax"].lower().rsplit("_", 1)[-1]
        accel_unit = _UNIT_SUFFIX_ACC.get(suf) if "_" in mapping["ax"] else None
        if accel_unit:
            notes.append(f"accelerometer unit {accel_unit} from the column name {mapping['ax']}")
    if not gyro_unit:
        name = mapping["gx"].lower()
        gyro_unit = next((u for s, u in _UNIT_SUFFIX_GYR.items() if name.endswith("_" + s)), None)
        if gyro_unit:
            notes.append(f"gyro unit {gyro_unit} from the column name {mapping['gx']}")
    au, gu = _need_units({"accel_unit": accel_unit, "gyro_unit": gyro_unit}, path.name)
    t = None
    if t_idx is not None:
        unit = time_unit
        if not unit:
            suf = mapping["t"].lower().rsplit("_", 1)[-1]
            unit = suf if "_" in mapping["t"] and suf in _TIME_SUFFIX else None
            if unit:
                notes.append(f"time unit {unit} from the column name {mapping['t']}")
        t = _time_seconds(t_raw, unit, f"the time column {mapping['t']!r}", detected, options)
    return from_arrays(data[:, :3], data[:, 3:6], t_s=t, rate_hz=rate_hz, accel_unit_name=au, gyro_unit_name=gu,
                       source=str(path), fmt="csv", notes=notes, detected=detected, options=options, copy=False,
                       **_common(opt))


def _read_headerless(path: Path, lay: Layout, *, columns: dict | None, time_unit: str | None,
                     rate_hz: float | None, accel_unit: str | None, gyro_unit: str | None, **opt) -> Recording:
    """A table of numbers without a header: columns by position (1-based in ``columns``)."""
    n = lay.ncols
    notes, detected, options = [], [], {}
    if columns:
        try:
            pos = {k: int(v) - 1 for k, v in columns.items()}
        except ValueError:
            raise RecordingError(f"{path.name} has no header row: map the columns by position (from 1), "
                                 "e.g. --columns ax=1,ay=2,az=3,gx=4,gy=5,gz=6[,t=7]") from None
        bad = [k for k in pos if k not in (*KEYS, "t")]
        if bad or not all(k in pos for k in KEYS) or not all(0 <= v < n for v in pos.values()):
            raise RecordingError(f"--columns: map ax ay az gx gy gz (and optionally t) to positions 1..{n}")
    elif n == 6:
        pos = dict(zip(KEYS, range(6)))
        notes.append("no header row: 6 columns read as ax ay az gx gy gz (map others with --columns ax=1,...)")
    elif n == 7:
        pos = dict(zip(("t",) + KEYS, range(7)))
        notes.append("no header row: 7 columns read as t ax ay az gx gy gz (map others with --columns ax=2,...)")
    else:
        raise RecordingError(f"{path.name} has no header row and {n} columns: map them by position with "
                             "--columns ax=1,ay=2,az=3,gx=4,gy=5,gz=6[,t=7]")
    rate_hz = _layout_lines(lay, rate_hz, "t" in pos, detected, notes, options)
    if rate_hz:
        pos.pop("t", None)
    use = [pos[k] for k in KEYS] + ([pos["t"]] if "t" in pos else [])
    data, t_raw = _load_table(path, lay.delim, use, lay.start, time_at=6 if "t" in pos else None,
                              budget=opt.get("memory_budget"))
    au, gu = _need_units({"accel_unit": accel_unit, "gyro_unit": gyro_unit}, path.name)
    t = None
    if "t" in pos:
        t = _time_seconds(t_raw, time_unit, f"{path.name}: the time column (position {pos['t'] + 1})",
                          detected, options)
    return from_arrays(data[:, :3], data[:, 3:6], t_s=t, rate_hz=rate_hz, accel_unit_name=au, gyro_unit_name=gu,
                       source=str(path), fmt="csv", notes=notes, detected=detected, options=options, copy=False,
                       **_common(opt))


# ------------------------------------------------------------------ imu_tk
def _imutk_file(path: Path, what: str, budget: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(t, xyz) of one of imu_tk's files: the time float64, the values float64 or float32 by the budget."""
    if not path.exists():
        raise RecordingError(f"{path}: no such file; check the path")
    _regular(path)
    try:
        lay = _layout(path)
        if lay.ncols != 4:
            raise RecordingError(f"{path} ({what}): {lay.ncols} columns per line; imu_tk's files have 4 (t x y z)")
        xyz, t = _load_table(path, lay.delim, [0, 1, 2, 3], lay.start, time_at=0, names=["t", "x", "y", "z"],
                             budget=budget)
    except RecordingError as e:
        if "columns per line" in str(e):
            raise
        raise RecordingError(f"not imu_tk's layout (lines of 't x y z' numbers): {e}") from None
    return t, xyz


#: the words that name imu_tk's accelerometer file, and those of its gyro file beside it (xsens_acc.mat, xsens_gyro.mat)
_ACC_WORDS = ("accelerometer", "accel", "acc")
_GYRO_WORDS = ("gyroscope", "gyro", "gyr")


def _imutk_pair(path: Path) -> Path | None:
    """The gyro file beside imu_tk's accelerometer file: its name with the accelerometer's word
    replaced by a gyro's (acc -> gyro, gyr, ...), when exactly one such file exists."""
    name = path.name
    low = name.lower()
    found = []
    for a in _ACC_WORDS:
        k = low.find(a)
        if k < 0:
            continue
        for g in _GYRO_WORDS:
            for cand in (name[:k] + g + name[k + len(a):], name[:k] + g.capitalize() + name[k + len(a):],
                         name[:k] + g.upper() + name[k + len(a):]):
                q = path.with_name(cand)
                if q.is_file() and q not in found:
                    found.append(q)
        break
    return found[0] if len(found) == 1 else None


def read_imutk(path: Path, *, gyro_file=None, accel_unit: str | None = None, gyro_unit: str | None = None,
               rate_hz: float | None = None, **opt) -> Recording:
    detected, options = [], {}
    if not gyro_file:
        if any(w in path.name.lower() for w in _GYRO_WORDS):
            raise RecordingError(f"{path.name} looks like imu_tk's gyro file (t x y z a line): imu_tk keeps the "
                                 "accelerometer and the gyro in separate files: give the accelerometer file with "
                                 "--from and this one with --gyro-file")
        gyro_file = _imutk_pair(path)
        if gyro_file is None:
            raise RecordingError(f"{path.name} has 4 numbers a line (imu_tk's layout, t x y z): imu_tk keeps the "
                                 "accelerometer and the gyro in separate files: give the gyro file with --gyro-file")
        detected.append(f"imu_tk's pair: the gyro file {gyro_file.name} beside it, by name (--gyro-file {gyro_file})")
        options["gyro_file"] = str(gyro_file)
    au, gu = _need_units({"accel_unit": accel_unit, "gyro_unit": gyro_unit}, "imu_tk's format")
    budget = opt.get("memory_budget")
    half = None if budget is None else max(memory.MIN_BUDGET_BYTES, budget // 2)
    ta, a = _imutk_file(path, "accelerometer", half)
    tg, g = _imutk_file(Path(gyro_file), "gyro", half)
    notes = []
    if len(ta) < 2:
        raise RecordingError(f"{path.name}: only {len(ta)} samples: a calibration needs minutes of data")
    if len(ta) != len(tg) or not _same_times(ta, tg):
        # not sample-synchronous: the gyro is interpolated at the accelerometer's times
        lo, hi = max(ta[0], tg[0]), min(ta[-1], tg[-1])
        keep = (ta >= lo) & (ta <= hi)
        ta, a = ta[keep], a[keep]
        if len(ta) < 3:
            raise RecordingError(f"{path.name} and {Path(gyro_file).name} do not overlap in time")
        g = np.column_stack([np.interp(ta, tg, g[:, j]) for j in range(3)]).astype(g.dtype, copy=False)
        notes.append("the gyro file's times differ from the accelerometer's: the gyro was interpolated "
                     "(linearly) at the accelerometer's times over their common span")
    del tg
    return from_arrays(a, g, t_s=ta, rate_hz=rate_hz, accel_unit_name=au, gyro_unit_name=gu,
                       source=f"{path} + {gyro_file}", fmt="imutk", notes=notes, detected=detected, options=options,
                       copy=False, **_common(opt))


def _same_times(ta: np.ndarray, tg: np.ndarray) -> bool:
    """True when two files' time stamps agree sample by sample within a quarter of the median step
    (compared a block at a time: no temporaries the size of the recording)."""
    atol = 0.25 * float(np.median(np.diff(ta[: 1_000_001])))
    for i in range(0, len(ta), 1 << 20):
        if not np.allclose(ta[i:i + (1 << 20)], tg[i:i + (1 << 20)], atol=atol):
            return False
    return True


# ------------------------------------------------------------------ imucal
def read_imucal(path: Path, *, rate_hz: float | None = None, accel_unit: str | None = None,
                gyro_unit: str | None = None, skip_rows: int | None = None, **opt) -> Recording:
    lay = _layout(path, skip_rows)
    cols, delim = lay.header or [], lay.delim
    low = [c.lower() for c in cols]
    if not rate_hz:
        raise RecordingError("imucal's CSV has a sample index, not a time: give --rate HZ "
                             "(imucal's example session: 102.4 Hz; its annotated counts file: 204.8 Hz)")
    au, gu = _need_units({"accel_unit": accel_unit, "gyro_unit": gyro_unit}, "imucal's CSV")
    need = ["acc_x", "acc_y", "acc_z", "gyr_x", "gyr_y", "gyr_z"]
    if not all(c in low for c in need):
        raise RecordingError(f"{path.name}: not imucal's layout (columns {', '.join(cols)}; expected "
                             f"{', '.join(need)})")
    idx = [low.index(c) for c in need]
    parts = None
    breaks = []
    notes = []
    if low[0] == "part":
        names = [r[0] for chunk, _ in _chunks(path, lay.start) for r in csv.reader(chunk, delimiter=delim)]
        data = _load(path, delim, idx, lay.start, budget=opt.get("memory_budget"))
        parts = []
        start = 0
        for i in range(1, len(names) + 1):
            if i == len(names) or names[i] != names[start]:
                parts.append((names[start], start, i))
                if i < len(names):
                    breaks.append((i, f"cut between parts {names[start]} and {names[i]} (imucal's annotated file "
                                      "is cut into parts: not continuous)"))
                start = i
        notes.append(f"{len(parts)} parts named in the file ({', '.join(p[0] for p in parts)}): each cut is a "
                     "break; the parts are not used to find the poses, only to compare with")
    else:
        data = _load(path, delim, idx, lay.start, budget=opt.get("memory_budget"))
    return from_arrays(data[:, :3], data[:, 3:], rate_hz=rate_hz, accel_unit_name=au, gyro_unit_name=gu,
                       source=str(path), fmt="imucal", breaks=breaks, notes=notes, parts=parts, **_common(opt))


def read_annotation(path) -> list[tuple[str, int, int]]:
    """imucal's section list (JSON: name -> {"start", "end"} sample indices), as (name, start, stop)."""
    try:
        d = json.loads(read_text(path, MAX_JSON_BYTES, "the section list"))
        return sorted(((str(k), int(v["start"]), int(v["end"])) for k, v in d.items()), key=lambda p: p[1])
    except FileRefused as e:
        raise RecordingError(str(e)) from None
    except (ValueError, KeyError, TypeError, AttributeError) as e:
        raise RecordingError(f"{path}: not imucal's section list (name: {{start, end}}): {e}") from None


def load_profile(path) -> dict:
    """A CSV profile (TOML): [columns] ax = "...", ..., t = "..."; [units] accel, gyro, time,
    accel_counts_per_g, gyro_counts_per_dps, accel_offset, gyro_offset; rate_hz; skip_rows (lines
    before the header row, for a preamble the reader cannot tell from the header); sensor.
    Returned as read() options."""
    import tomllib
    try:
        d = tomllib.loads(read_text(path, MAX_JSON_BYTES, "profile"))
    except FileRefused as e:
        raise RecordingError(str(e)) from None
    except (OSError, tomllib.TOMLDecodeError) as e:
        raise RecordingError(f"profile {path}: {e}") from None
    known = {"columns", "units", "rate_hz", "format", "device", "skip_rows", "sensor"}
    extra = set(d) - known
    if extra:
        raise RecordingError(f"profile {path}: unknown key(s) {', '.join(sorted(extra))}; "
                             f"known: {', '.join(sorted(known))}")
    u = d.get("units", {})
    out = {"columns": {k: v for k, v in d.get("columns", {}).items() if k != "t"},
           "time_column": d.get("columns", {}).get("t"), "time_unit": u.get("time"),
           "accel_unit": u.get("accel"), "gyro_unit": u.get("gyro"),
           "accel_counts_per_g": u.get("accel_counts_per_g"), "gyro_counts_per_dps": u.get("gyro_counts_per_dps"),
           "rate_hz": d.get("rate_hz"), "format": d.get("format"), "device": d.get("device"),
           "skip_rows": d.get("skip_rows"), "sensor": d.get("sensor"), "accel_offset": u.get("accel_offset"),
           "gyro_offset": u.get("gyro_offset")}
    return {k: v for k, v in out.items() if v not in (None, {})}

