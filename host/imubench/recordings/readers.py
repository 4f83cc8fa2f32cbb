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
import zipfile
from pathlib import Path

import numpy as np

from imubench.files import (
    MAX_CAPTURE_BYTES,
    MAX_JSON_BYTES,
    MAX_LINE_CHARS,
    FileRefused,
    MiB,
    bounded_lines,
    open_input,
    read_bytes,
    read_text,
)
from imubench.recordings import FORMATS, Recording, RecordingError, from_arrays

#: the most samples a recording may hold (21 columns of float64 at most: about 3 GiB); a calibration
#: needs minutes of data, not days
MAX_SAMPLES = 20_000_000
#: the lines parsed at a time: text is never held whole, only this many lines of it
CHUNK_LINES = 65536
#: what the arrays of one .npz member may take once read (checked from its header before reading)
MAX_NPZ_MEMBER_BYTES = 1024 * MiB

KEYS = ("ax", "ay", "az", "gx", "gy", "gz")
_CANDIDATES = {
    "accel": [("acc_x", "acc_y", "acc_z"), ("ax", "ay", "az"), ("accel_x", "accel_y", "accel_z"),
              ("accx", "accy", "accz"), ("ax_mps2", "ay_mps2", "az_mps2"), ("ax_g", "ay_g", "az_g"),
              ("linear_acceleration_x", "linear_acceleration_y", "linear_acceleration_z")],
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


def _header(path: Path) -> tuple[list[str], str]:
    with _open_text(path) as f:
        for line in _lines(f, path):
            if line.strip() and not line.lstrip().startswith("#"):
                break
        else:
            raise RecordingError(f"{path} is empty")
    try:
        delim = csv.Sniffer().sniff(line, delimiters=",;\t ").delimiter
    except csv.Error:
        delim = ","
    cols = [c.strip() for c in next(csv.reader([line], delimiter=delim))]
    return cols, delim


def _numeric(cols: list[str]) -> bool:
    """True when every field of a line is a number (a headerless table)."""
    try:
        [float(c) for c in cols]
    except ValueError:
        return False
    return bool(cols)


def _chunks(path: Path, header: bool):
    """Lists of at most CHUNK_LINES data lines of a text file (after its header line when it has
    one; blank lines and # comments skipped): the file is streamed, never held whole."""
    with _open_text(path) as f:
        lines = _lines(f, path)
        if header:
            for line in lines:
                if line.strip() and not line.lstrip().startswith("#"):
                    break
        chunk = []
        for line in lines:
            if line.strip() and not line.lstrip().startswith("#"):
                chunk.append(line)
                if len(chunk) == CHUNK_LINES:
                    yield chunk
                    chunk = []
        if chunk:
            yield chunk


def _load(path: Path, delim: str | None, usecols: list[int] | None, header: bool = True) -> np.ndarray:
    """The numbers of the columns usecols (all when None) of a text table, parsed CHUNK_LINES
    lines at a time into one array sized from the file's size (bounded memory: the text of one
    chunk and the numbers read; no second copy)."""
    out, n = None, 0
    size = path.stat().st_size
    try:
        for chunk in _chunks(path, header):
            a = np.loadtxt(chunk, delimiter=None if delim in (" ", None) else delim, usecols=usecols,
                           comments="#", ndmin=2, dtype=np.float64)
            if out is None:
                per_line = max(1.0, sum(map(len, chunk)) / len(chunk))
                rows = len(a) if len(chunk) < CHUNK_LINES or path.suffix == ".gz" else int(size / per_line * 1.02)
                out = np.empty((min(max(rows, len(a)), MAX_SAMPLES + 1), a.shape[1]))
            elif a.shape[1] != out.shape[1]:
                raise ValueError(f"{a.shape[1]} columns after {n} lines of {out.shape[1]}")
            if n + len(a) > MAX_SAMPLES:
                raise RecordingError(f"{path}: more than the limit of {MAX_SAMPLES} samples; cut the recording "
                                     "(a calibration needs minutes of data)")
            if n + len(a) > len(out):
                out = np.resize(out, (min(max(n + len(a), int(len(out) * 1.5)), MAX_SAMPLES + 1), out.shape[1]))
            out[n:n + len(a)] = a
            n += len(a)
    except RecordingError:
        raise
    except ValueError as e:
        raise RecordingError(f"{path}: not numbers where numbers are expected ({' '.join(str(e).split())[:160]}); "
                             "check the delimiter and the header") from None
    if out is None:
        return np.empty((0, len(usecols) if usecols else 0))
    return out[:n]


def detect_format(path) -> str:
    """The format of a file by its extension and header (the choice is printed by the caller)."""
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
    if ext.startswith(".csv") or ext.startswith(".txt"):
        cols, _ = _header(p)
        low = [c.lower() for c in cols]
        if low[:1] == ["n_samples"] or low[:2] == ["part", "samples"]:
            return "imucal"
        return "csv"
    try:                                  # any other name: a text table of numbers is read as csv
        cols, _ = _header(p)
    except (UnicodeDecodeError, OSError):
        cols = []
    if len(cols) in (6, 7) and _numeric(cols):
        return "csv"
    raise RecordingError(f"cannot tell the format of {p.name} from its name: give --format "
                         f"({'|'.join(FORMATS)})")


def read(path, fmt: str | None = None, **opt) -> Recording:
    p = Path(path)
    if not p.exists():
        raise RecordingError(f"{p}: no such file or directory; check the path")
    if not p.is_dir():
        _regular(p)                 # a FIFO or a device is refused before anything reads it
    fmt = fmt or detect_format(p)
    if fmt not in FORMATS:
        raise RecordingError(f"unknown format {fmt!r}; one of {', '.join(FORMATS)}")
    return {"csv": read_csv, "imutk": read_imutk, "imucal": read_imucal, "npz": read_npz,
            "capture": read_capture, "rosbag": read_rosbag}[fmt](p, **opt)


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
                             "--accel-scale COUNTS_PER_G / --gyro-scale COUNTS_PER_DPS if known)")
    return au, gu


def _common(opt: dict) -> dict:
    return {"accel_counts_per_g": opt.get("accel_counts_per_g"), "gyro_counts_per_dps": opt.get("gyro_counts_per_dps"),
            "device": opt.get("device")}


# ------------------------------------------------------------------ csv
def read_csv(path: Path, *, columns: dict | None = None, time_column: str | None = None,
             time_unit: str | None = None, rate_hz: float | None = None, accel_unit: str | None = None,
             gyro_unit: str | None = None, **opt) -> Recording:
    cols, delim = _header(path)
    if _numeric(cols):
        return _read_headerless(path, cols, delim, columns=columns, time_unit=time_unit, rate_hz=rate_hz,
                                accel_unit=accel_unit, gyro_unit=gyro_unit, **opt)
    low = {c.lower(): i for i, c in enumerate(cols)}
    notes = []
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
    if found_by_name:
        notes.append("columns found by name: " + "; ".join(found_by_name) + " (map others with --columns)")
    missing = [v for v in mapping.values() if v.lower() not in low]
    if missing:
        raise RecordingError(f"{path.name} has no column {missing[0]!r}; its columns are {', '.join(cols)}")
    idx = [low[mapping[k].lower()] for k in KEYS]
    t_idx = low[mapping["t"].lower()] if "t" in mapping else None
    data = _load(path, delim, idx + ([t_idx] if t_idx is not None else []))
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
        if not unit:
            raise RecordingError(f"the time column {mapping['t']!r} does not say its unit: give --time-unit "
                                 "s|ms|us|ns (or --rate HZ to ignore it)")
        if unit not in _TIME_SUFFIX:
            raise RecordingError(f"--time-unit {unit!r}: one of s, ms, us, ns")
        t = data[:, 6] * _TIME_SUFFIX[unit]
    return from_arrays(data[:, :3], data[:, 3:6], t_s=t, rate_hz=rate_hz, accel_unit_name=au, gyro_unit_name=gu,
                       source=str(path), fmt="csv", notes=notes, **_common(opt))


def _read_headerless(path: Path, cols: list[str], delim: str, *, columns: dict | None, time_unit: str | None,
                     rate_hz: float | None, accel_unit: str | None, gyro_unit: str | None, **opt) -> Recording:
    """A table of numbers without a header: columns by position (1-based in ``columns``)."""
    n = len(cols)
    notes = []
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
    if rate_hz:
        pos.pop("t", None)
    use = [pos[k] for k in KEYS] + ([pos["t"]] if "t" in pos else [])
    data = _load(path, delim, use, header=False)
    au, gu = _need_units({"accel_unit": accel_unit, "gyro_unit": gyro_unit}, path.name)
    t = None
    if "t" in pos:
        if not time_unit:
            raise RecordingError(f"{path.name}: the time column (position {pos['t'] + 1}) does not say its unit: "
                                 "give --time-unit s|ms|us|ns, or --rate HZ to ignore it")
        if time_unit not in _TIME_SUFFIX:
            raise RecordingError(f"--time-unit {time_unit!r}: one of s, ms, us, ns")
        t = data[:, 6] * _TIME_SUFFIX[time_unit]
    return from_arrays(data[:, :3], data[:, 3:6], t_s=t, rate_hz=rate_hz, accel_unit_name=au, gyro_unit_name=gu,
                       source=str(path), fmt="csv", notes=notes, **_common(opt))


# ------------------------------------------------------------------ imu_tk
def _imutk_file(path: Path, what: str) -> np.ndarray:
    if not path.exists():
        raise RecordingError(f"{path}: no such file; check the path")
    _regular(path)
    try:
        d = _load(path, None, None, header=False)
    except RecordingError as e:
        raise RecordingError(f"not imu_tk's layout (lines of 't x y z' numbers): {e}") from None
    if d.shape[1] != 4:
        raise RecordingError(f"{path} ({what}): {d.shape[1]} columns per line; imu_tk's files have 4 (t x y z)")
    return d


def read_imutk(path: Path, *, gyro_file=None, accel_unit: str | None = None, gyro_unit: str | None = None,
               rate_hz: float | None = None, **opt) -> Recording:
    if not gyro_file:
        raise RecordingError("imu_tk keeps the accelerometer and the gyro in separate files: give the "
                             "accelerometer file with --from and the gyro file with --gyro-file")
    au, gu = _need_units({"accel_unit": accel_unit, "gyro_unit": gyro_unit}, "imu_tk's format")
    a = _imutk_file(path, "accelerometer")
    g = _imutk_file(Path(gyro_file), "gyro")
    notes = []
    if len(a) != len(g) or not np.allclose(a[:, 0], g[:, 0], atol=0.25 * float(np.median(np.diff(a[:, 0])))):
        # not sample-synchronous: the gyro is interpolated at the accelerometer's times
        lo, hi = max(a[0, 0], g[0, 0]), min(a[-1, 0], g[-1, 0])
        a = a[(a[:, 0] >= lo) & (a[:, 0] <= hi)]
        if len(a) < 3:
            raise RecordingError(f"{path.name} and {Path(gyro_file).name} do not overlap in time")
        g = np.column_stack([a[:, 0]] + [np.interp(a[:, 0], g[:, 0], g[:, j]) for j in (1, 2, 3)])
        notes.append("the gyro file's times differ from the accelerometer's: the gyro was interpolated "
                     "(linearly) at the accelerometer's times over their common span")
    return from_arrays(a[:, 1:], g[:, 1:], t_s=a[:, 0], rate_hz=rate_hz, accel_unit_name=au, gyro_unit_name=gu,
                       source=f"{path} + {gyro_file}", fmt="imutk", notes=notes, **_common(opt))


# ------------------------------------------------------------------ imucal
def read_imucal(path: Path, *, rate_hz: float | None = None, accel_unit: str | None = None,
                gyro_unit: str | None = None, **opt) -> Recording:
    cols, delim = _header(path)
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
        names = [r[0] for chunk in _chunks(path, header=True) for r in csv.reader(chunk, delimiter=delim)]
        data = _load(path, delim, idx)
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
        data = _load(path, delim, idx)
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


# ------------------------------------------------------------------ our captures
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


def read_npz(path: Path, **opt) -> Recording:
    _check_npz(path)
    try:
        z = np.load(path)
    except (ValueError, OSError) as e:
        raise RecordingError(f"{path}: not a .npz file ({e})") from None
    need = ("accel_mps2", "rate_rad_s")
    if not all(k in z for k in need):
        raise RecordingError(f"{path.name} holds {', '.join(z.files)}; imubench's npz (imubench decode --npz) "
                             f"has {', '.join(need)} and t_us")
    breaks = []
    notes = []
    t = z["t_us"] * 1e-6 if "t_us" in z else None
    if "sample_index" in z:
        si = np.asarray(z["sample_index"], np.int64)
        for k in np.flatnonzero(np.diff(si) > 1):
            breaks.append((int(k + 1), f"{int(si[k + 1] - si[k] - 1)} samples lost on the link before sample {k + 1}"))
    if "status" in z and np.any(z["status"]):
        notes.append(f"{int(np.count_nonzero(z['status']))} samples flagged bad by the device (status bits)")
    rec = from_arrays(z["accel_mps2"], z["rate_rad_s"], t_s=t, rate_hz=opt.get("rate_hz"), source=str(path),
                      fmt="npz", notes=notes, device=opt.get("device"))
    rec.breaks = sorted(rec.breaks + [b for b in breaks if b[0] not in {x[0] for x in rec.breaks}])
    return rec


def read_capture(path: Path, **opt) -> Recording:
    from imubench.wire.decoder import decode_bytes
    try:
        data = read_bytes(path, MAX_CAPTURE_BYTES, "the capture")
    except FileRefused as e:
        raise RecordingError(str(e)) from None
    _, raw, cal, st = decode_bytes(data)
    block = raw if raw is not None else cal
    if block is None or len(block) < 3:
        raise RecordingError(f"{path.name}: no samples decoded (frames ok {st.frames_ok}, rejected "
                             f"{st.frames_rejected}); is it a capture-N.bin of an imubench session?")
    acc, gyr = block.si()
    notes = [f"{'raw' if raw is not None else 'calibrated'} samples of an imubench device, nominal scaling"]
    breaks = []
    si = np.asarray(block.sample_index, np.int64)
    for k in np.flatnonzero(np.diff(si) > 1):
        breaks.append((int(k + 1), f"{int(si[k + 1] - si[k] - 1)} samples lost on the link before sample {k + 1}"))
    rec = from_arrays(acc, gyr, t_s=block.t_us * 1e-6, source=str(path), fmt="capture", notes=notes,
                      device=opt.get("device"))
    rec.breaks = sorted(rec.breaks + [b for b in breaks if b[0] not in {x[0] for x in rec.breaks}])
    return rec


# ------------------------------------------------------------------ ROS bags
INSTALL_ROSBAGS = "pip install 'imubench[rosbag]' (the rosbags library)"


def read_rosbag(path: Path, *, topic: str | None = None, **opt) -> Recording:
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise RecordingError(f"reading ROS bags needs the optional rosbags library: {INSTALL_ROSBAGS}") from None
    try:
        reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except Exception as e:  # noqa: BLE001 - rosbags raises its own classes for every damaged bag
        raise RecordingError(f"{path}: not a readable ROS bag ({type(e).__name__}: {e})") from None
    try:
        imu = [c for c in reader.connections if c.msgtype in ("sensor_msgs/msg/Imu", "sensor_msgs/Imu")]
        if not imu:
            raise RecordingError(f"{path.name} has no sensor_msgs/Imu topic (topics: "
                                 f"{', '.join(sorted({c.topic for c in reader.connections})) or 'none'})")
        topics = sorted({c.topic for c in imu})
        if topic is None and len(topics) > 1:
            raise RecordingError(f"{path.name} has several sensor_msgs/Imu topics ({', '.join(topics)}): "
                                 "choose one with --topic")
        topic = topic or topics[0]
        conns = [c for c in imu if c.topic == topic]
        if not conns:
            raise RecordingError(f"{path.name} has no sensor_msgs/Imu topic {topic!r} (it has {', '.join(topics)})")
        t, a, g, recv = [], [], [], []
        for c, ts, raw in reader.messages(connections=conns):
            m = reader.deserialize(raw, c.msgtype)
            t.append(m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec)
            recv.append(ts * 1e-9)
            la, av = m.linear_acceleration, m.angular_velocity
            a.append((la.x, la.y, la.z))
            g.append((av.x, av.y, av.z))
    finally:
        reader.close()
    notes = [f"topic {topic}: {len(t)} sensor_msgs/Imu messages (m/s², rad/s by the message definition, REP 103)"]
    t = np.asarray(t)
    if len(t) and not np.any(np.diff(t) > 0):
        t = np.asarray(recv)
        notes.append("the messages' header stamps are not set: the bag's receive times are used")
    return from_arrays(np.asarray(a), np.asarray(g), t_s=t, source=str(path), fmt="rosbag", notes=notes,
                       device=opt.get("device"))


def load_profile(path) -> dict:
    """A CSV profile (TOML): [columns] ax = "...", ..., t = "..."; [units] accel, gyro, time,
    accel_counts_per_g, gyro_counts_per_dps; rate_hz. Returned as read() options."""
    import tomllib
    try:
        d = tomllib.loads(read_text(path, MAX_JSON_BYTES, "profile"))
    except FileRefused as e:
        raise RecordingError(str(e)) from None
    except (OSError, tomllib.TOMLDecodeError) as e:
        raise RecordingError(f"profile {path}: {e}") from None
    known = {"columns", "units", "rate_hz", "format", "device"}
    extra = set(d) - known
    if extra:
        raise RecordingError(f"profile {path}: unknown key(s) {', '.join(sorted(extra))}; "
                             f"known: {', '.join(sorted(known))}")
    u = d.get("units", {})
    out = {"columns": {k: v for k, v in d.get("columns", {}).items() if k != "t"},
           "time_column": d.get("columns", {}).get("t"), "time_unit": u.get("time"),
           "accel_unit": u.get("accel"), "gyro_unit": u.get("gyro"),
           "accel_counts_per_g": u.get("accel_counts_per_g"), "gyro_counts_per_dps": u.get("gyro_counts_per_dps"),
           "rate_hz": d.get("rate_hz"), "format": d.get("format"), "device": d.get("device")}
    return {k: v for k, v in out.items() if v not in (None, {})}

