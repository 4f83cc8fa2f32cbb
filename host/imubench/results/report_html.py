"""The pieces every section of the HTML report is built from: escaping, numbers, tables,
embedded plots (read safely: a regular PNG within its directory, of bounded size) and the
loading of the parts a report joins (refusing a part from another device)."""
from __future__ import annotations

import base64
import html
import json
import math
import os
import stat
from collections.abc import Sequence
from pathlib import Path

from imubench import units as U

from imubench.files import MAX_JSON_BYTES
from imubench.wire.ids import byte_ids_text, pid_text, sn_text

G0 = U.G0_MPS2
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
MAX_PLOT_BYTES = 16 * 1024 * 1024     # an embedded plot: ours are ~100 kB


def esc(x) -> str:
    return html.escape("" if x is None else str(x), quote=True)


def _f(x) -> float:
    try:
        return float(x)
    except (TypeError, ValueError):
        return math.nan


def _num(x, fmt="{:.6g}") -> str:
    v = _f(x)
    return "–" if not math.isfinite(v) else fmt.format(v)


class Refused(ValueError):
    """A file the report will not embed; the message says why."""


def read_png(path, within=None, max_bytes: int = MAX_PLOT_BYTES) -> bytes | None:
    """The bytes of the PNG at path; None when there is no such file. Raises Refused for
    anything else than a regular PNG file of at most max_bytes, or (with `within`) one whose
    real path (symlinks resolved) is outside the directory `within`: a report is sent on its
    own, so it carries no file from elsewhere on the disk, and never blocks (a FIFO) or reads
    without end (a device)."""
    data = read_within(path, within, max_bytes)
    if data is not None and not data.startswith(PNG_MAGIC):
        raise Refused(f"{path} is not a PNG")
    return data


def read_json_within(path, within=None, max_bytes: int = MAX_JSON_BYTES):
    """The JSON at path, read as read_within reads (a symlink out of `within`, by default the
    directory the file is named in, is refused: the report embeds no file from elsewhere);
    None when there is no such file. Raises Refused, or ValueError when it does not parse."""
    path = Path(path).absolute()
    data = read_within(path, path.parent if within is None else within, max_bytes)
    return None if data is None else json.loads(data)


def read_within(path, within=None, max_bytes: int = MAX_PLOT_BYTES) -> bytes | None:
    """The bytes of the regular file at path (at most max_bytes; never a FIFO or a device),
    None when there is none; with `within`, refused unless its real path is inside it."""
    path = Path(path)
    if within is not None:
        base = Path(within).resolve()
        real = (base / path).resolve() if not path.is_absolute() else path.resolve()
        if not real.is_relative_to(base):
            raise Refused(f"{path} is outside {base}")
        path = real
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_NOCTTY", 0))
    except FileNotFoundError:
        return None
    except OSError as e:
        raise Refused(f"{path}: {e.strerror or e}") from None
    with os.fdopen(fd, "rb") as fh:
        st = os.fstat(fh.fileno())
        if not stat.S_ISREG(st.st_mode):
            raise Refused(f"{path} is not a regular file")
        if st.st_size > max_bytes:
            raise Refused(f"{path} is {st.st_size} bytes, more than the limit of {max_bytes}")
        data = fh.read(max_bytes + 1)
    if len(data) > max_bytes:
        raise Refused(f"{path} is more than the limit of {max_bytes} bytes")
    return data


def png_data_uri(path, within=None) -> str | None:
    """The PNG at path as a data URI, or None if it is missing or refused (read_png)."""
    try:
        data = read_png(path, within)
    except Refused:
        return None
    return None if data is None else "data:image/png;base64," + base64.b64encode(data).decode("ascii")


def _png(path, within=None) -> tuple[str | None, str | None]:
    """(data URI, None), (None, None) when there is no file, or (None, why it was refused)."""
    try:
        data = read_png(path, within)
    except Refused as e:
        return None, str(e)
    return (None if data is None else "data:image/png;base64," + base64.b64encode(data).decode("ascii")), None


def _img(uri: str | None, alt: str, refused: str | None = None) -> str:
    if refused is not None:
        return f'<p class="missing">{esc(alt)}: plot refused, not embedded ({esc(refused)})</p>'
    if uri is None:
        return f'<p class="missing">{esc(alt)}: plot not available</p>'
    return f'<p><img src="{uri}" alt="{esc(alt)}"></p>'


def _badge(label: str, value) -> str:
    cls = "na" if value is None else ("ok" if value else "bad")
    word = "n/a" if value is None else ("yes" if value else "NO")
    return f'<span class="badge {cls}">{esc(label)}: {word}</span>'


def _table(header: Sequence[str], rows: Sequence[Sequence], left: int = 1) -> str:
    """rows of already-escaped HTML cells; the first `left` columns are left-aligned."""
    h = "".join(f'<th class="{"l" if i < left else ""}">{c}</th>' for i, c in enumerate(header))
    body = "".join("<tr>" + "".join(f'<td class="{"l" if i < left else ""}">{c}</td>' for i, c in enumerate(r))
                   + "</tr>" for r in rows)
    return f"<table><thead><tr>{h}</tr></thead><tbody>{body}</tbody></table>"


def _missing(what: str, how: str) -> str:
    return f'<p class="missing">{esc(what)}: not measured in this session ({esc(how)}).</p>'


def _load_json(path: Path | None, what: str, how: str, out: list[str], within=None):
    """The JSON at path, or None after appending to out why there is none: "not measured"
    (with how to get it) when the file is absent, "refused" when it is a link out of `within`
    (default: its own directory) or not a regular file, "unreadable" when it does not parse."""
    try:
        data = None if path is None else read_json_within(path, within)
    except Refused as e:
        out.append(f'<p class="foreign"><b>refused</b>: {esc(what)} data not embedded ({esc(e)}).</p>')
        return None
    except (OSError, ValueError) as e:
        out.append(f'<p class="missing">{esc(what)} data {esc(path)}: unreadable ({esc(e)}); '
                   "not measured in this session.</p>")
        return None
    if data is None:
        out.append(_missing(what, how))
    return data


def _version() -> str:
    try:
        from importlib.metadata import version
        return version("imubench")
    except Exception:  # noqa: BLE001 - not installed as a distribution
        return "unknown"


def _foreign(data, session_uid: str | None, what: str) -> tuple[str | None, str]:
    """(refusal HTML or None, state) for a result file checked against the session's device:
    "same", "foreign" (another MCU UID: refused, its numbers are not shown), "unnamed" (the
    file names no device: shown with a warning) or "unknown" (the session names none)."""
    dev = data.get("device") if isinstance(data, dict) else None
    uid = str(dev.get("mcu_uid", "")).upper() if isinstance(dev, dict) else ""
    if not session_uid:
        return None, "unknown"
    if not uid:
        return None, "unnamed"
    if uid != session_uid:
        return (f'<p class="foreign"><b>refused: from another device.</b> This {esc(what)} was measured on '
                f'<span class="mono">{esc(uid)}</span>, not on this session\'s device '
                f'<span class="mono">{esc(session_uid)}</span>; its numbers are not part of this report.</p>'), "foreign"
    return None, "same"


def _load_part(path: Path | None, what: str, how: str, out: list[str], session_uid: str | None, label: str,
               within=None):
    """_load_json, then the device check: None (after appending why to out) when the file is
    missing, unreadable or from another device; a note is appended when it names no device."""
    data = _load_json(path, what, how, out, within)
    if data is None:
        return None
    refusal, state = _foreign(data, session_uid, label)
    if refusal:
        out.append(refusal)
        return None
    if state == "unnamed":
        out.append(_unnamed_note(label))
    return data


def _unnamed_note(what: str) -> str:
    return (f'<p class="note">this {esc(what)} does not name its device (recorded by an older imubench): '
            "it cannot be checked against the session's device.</p>")


# ------------------------------------------------------------------ calibration
def _id_text(key: str, v) -> str:
    """Identifiers in the one format `imubench info` prints (imubench.wire.ids)."""
    fmt = {"accel_ids": byte_ids_text, "gyro_pid": lambda xs: " ".join(pid_text(x) for x in xs),
           "gyro_sn": lambda xs: " ".join(sn_text(x) for x in xs)}.get(key)
    if fmt is not None and isinstance(v, list) and all(isinstance(x, int) for x in v):
        return fmt(v)
    if key == "mcu_uid" and isinstance(v, str):
        return v.upper()
    return ", ".join(map(str, v)) if isinstance(v, list) else str(v)
