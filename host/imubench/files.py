"""Files that are only what they claim (the bottom layer: imports only imubench.errors).

Every file the host writes goes through this module's writers and every file it reads whole
through its readers, so that

- an output never follows a link: every folder on its path is opened one component at a
  time with O_NOFOLLOW | O_DIRECTORY (openat; make_dir creates the missing ones the same
  way), so a planted ``slot-1 -> ../victimdir`` anywhere on the path is refused, not
  followed; a finished file is written to a fresh temporary file created in that folder
  (O_EXCL | O_NOFOLLOW, a random name, so a link left at ``NAME.tmp`` is never written
  through) and renamed over the final name; a symlink at the final name is refused, not
  replaced or followed. Files written as they grow (a capture, a CSV log) are opened with
  O_NOFOLLOW relative to their folder and must be regular files with one link (a hard link
  would grow another file); a capture is always a new file (O_EXCL): an existing one is
  refused, never appended to;
- an input is a regular file (a FIFO, a device such as /dev/zero or a directory is refused at
  once instead of hanging or reading without end), and what is read whole is bounded: the
  size is checked before reading and the limit named when it is hit.

Errors are FileRefused (an ImubenchError): one line naming the file and what to do.
"""
from __future__ import annotations

import contextlib
import errno
import io
import os
import stat
import tempfile
from pathlib import Path
from typing import Iterator

from imubench.errors import ImubenchError

MiB = 1 << 20
#: what a JSON or TOML input (a session, a profile, a result file) may weigh: far above any we write
MAX_JSON_BYTES = 64 * MiB
#: the longest line a text input (CSV, imu_tk) may have
MAX_LINE_CHARS = 1 * MiB
#: a raw capture (capture-N.bin, a decode input) is read whole: about 5 hours of samples at 1 kHz
MAX_CAPTURE_BYTES = 1024 * MiB
#: a firmware image or a parameter page
MAX_IMAGE_BYTES = 16 * MiB

_NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)
_NOCTTY = getattr(os, "O_NOCTTY", 0)
_NONBLOCK = getattr(os, "O_NONBLOCK", 0)


class FileRefused(ImubenchError):
    """A file that is not what it must be (a symlink where an output goes, a FIFO or a device
    where a regular input file is expected, an input above its size limit)."""


def kind_of(mode: int) -> str:
    """What a file of this st_mode is, in words ("a FIFO (named pipe)", "a regular file")."""
    return "a regular file" if stat.S_ISREG(mode) else _kind(mode)


def _kind(mode: int) -> str:
    for test, name in ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISSOCK, "a socket"), (stat.S_ISLNK, "a symbolic link")):
        if test(mode):
            return name
    return "not a regular file"


# ------------------------------------------------------------------ outputs
_DIRFLAGS = os.O_RDONLY | getattr(os, "O_DIRECTORY", 0) | _NOFOLLOW | getattr(os, "O_CLOEXEC", 0)
_OPENAT = os.open in os.supports_dir_fd and os.mkdir in os.supports_dir_fd and bool(_NOFOLLOW)


def open_dir(path: str | os.PathLike, create: bool = True, _depth: int = 0) -> int:
    """A descriptor of the folder path, reached one component at a time without following a
    link at any of them (openat with O_NOFOLLOW | O_DIRECTORY); missing folders are made on
    the way when create. A symlink or a non-folder on the way is a FileRefused naming it,
    but for the system's own links at the top of the tree (root's, in /: /tmp -> private/tmp
    and /var on macOS, /home on some systems), which no other user can plant. (Where openat
    is missing, Windows, each component is checked with lstat instead.)"""
    path = Path(path)
    if not _OPENAT:
        if create:
            path.mkdir(parents=True, exist_ok=True)
        _check_components(path)
        return os.open(path, os.O_RDONLY)
    parts = path.parts
    start = parts[0] if path.is_absolute() else "."
    fd = os.open(start, _DIRFLAGS & ~_NOFOLLOW)       # "/" or the working folder: where the user is
    done = Path(start)
    try:
        for name in parts[1:] if path.is_absolute() else parts:
            if name in ("", "."):
                continue
            done = done / name
            try:
                nfd = os.open(name, _DIRFLAGS, dir_fd=fd)
            except FileNotFoundError:
                if not create:
                    raise FileRefused(f"{done} does not exist; make the folder first or choose another") from None
                try:
                    os.mkdir(name, 0o777, dir_fd=fd)
                except FileExistsError:
                    pass                            # made meanwhile: opened (and checked) below
                nfd = os.open(name, _DIRFLAGS, dir_fd=fd)
            except OSError as e:
                if e.errno in (errno.ELOOP, errno.ENOTDIR, errno.EMLINK):
                    system = _system_link(fd, name) if path.is_absolute() and done.parent == Path(start) else None
                    if system is not None and _depth < 4:
                        os.close(fd)
                        fd = -1
                        rest = Path(*parts[2:]) if len(parts) > 2 else Path()
                        return open_dir(Path(system) / rest, create, _depth + 1)
                    _refuse_component(done, fd, name)
                raise
            os.close(fd)
            fd = nfd
        return fd
    except BaseException:
        if fd >= 0:
            os.close(fd)
        raise


def _system_link(fd: int, name: str) -> str | None:
    """The target of the link name in / (fd), if it is the system's: owned by root in a root
    folder no one else may write."""
    try:
        st = os.lstat(name, dir_fd=fd)
        top = os.fstat(fd)
    except OSError:
        return None
    if not stat.S_ISLNK(st.st_mode) or st.st_uid != 0 or top.st_uid != 0 or top.st_mode & 0o022:
        return None
    return os.path.normpath(os.path.join("/", os.readlink(name, dir_fd=fd)))


def _refuse_component(done: Path, fd: int, name: str):
    st = os.lstat(name, dir_fd=fd)
    if stat.S_ISLNK(st.st_mode):
        raise FileRefused(f"{done} is a symbolic link (to {os.readlink(name, dir_fd=fd)}); imubench writes only "
                          "into real folders, never through a link: remove it or give the real path") from None
    raise FileRefused(f"{done} is {kind_of(st.st_mode)}, not a folder; choose another output folder") from None


def _check_components(path: Path) -> None:
    p = Path(path.anchor) if path.is_absolute() else Path(".")
    for name in path.parts[1:] if path.is_absolute() else path.parts:
        p = p / name
        st = os.lstat(p)
        if stat.S_ISLNK(st.st_mode):
            raise FileRefused(f"{p} is a symbolic link; imubench writes only into real folders, never through "
                              "a link: remove it or give the real path")


def make_dir(path: str | os.PathLike) -> Path:
    """Make the folder path (and its parents) without following a link at any component
    (open_dir); path is returned. An existing folder is fine."""
    os.close(open_dir(path, create=True))
    return Path(path)


def _parent(path: Path) -> Path:
    return path.parent if str(path.parent) else Path(".")


def check_output(path: str | os.PathLike) -> Path:
    """path, after refusing a symlink or anything but a regular file at it (a missing file is
    fine)."""
    path = Path(path)
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return path
    if stat.S_ISLNK(st.st_mode):
        raise FileRefused(f"{path} is a symbolic link; imubench does not write through links it did not "
                          "create: remove it or choose another output name")
    if not stat.S_ISREG(st.st_mode):
        raise FileRefused(f"{path} is {_kind(st.st_mode)}, not a regular file; choose another output name")
    return path


def _read_umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


_UMASK = _read_umask()      # read once: os.umask is process-wide, reading it races with threads


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike, binary: bool = False, encoding: str = "utf-8",
                  newline: str | None = None) -> Iterator[io.IOBase]:
    """A file object whose content replaces path when the block ends without an exception
    (else nothing changes and the temporary file is removed). The temporary file is created
    beside path with a random name (O_EXCL | O_NOFOLLOW: mkstemp), flushed to the disk, given
    the usual permissions (0666 less the umask) and renamed over path (os.replace, atomic on
    POSIX and Windows). A symlink or a non-regular file at path is refused (FileRefused)."""
    path = check_output(path)
    if not _OPENAT:
        yield from _atomic_output_portable(path, binary, encoding, newline)
        return
    dfd = open_dir(_parent(path), create=False)
    try:
        _check_at(dfd, path)
        import secrets
        tmp = f".{path.name}.{secrets.token_hex(6)}.tmp"
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | _NOFOLLOW | getattr(os, "O_CLOEXEC", 0),
                     0o666 & ~_UMASK, dir_fd=dfd)
        try:
            yield from _synced(fd, binary, encoding, newline)
            _check_at(dfd, path)        # a link planted while we wrote is refused too
            os.replace(tmp, path.name, src_dir_fd=dfd, dst_dir_fd=dfd)
        except BaseException:
            with contextlib.suppress(OSError):
                os.unlink(tmp, dir_fd=dfd)
            raise
    finally:
        os.close(dfd)


def _synced(fd: int, binary: bool, encoding: str, newline):
    """The body both atomic writers share: the temporary file fd given the usual permissions
    (0666 less the umask), yielded as a file object, and flushed to the disk when the block ends
    (closed in any case; an exception from the block passes through)."""
    if hasattr(os, "fchmod"):
        os.fchmod(fd, 0o666 & ~_UMASK)
    with (os.fdopen(fd, "wb") if binary else os.fdopen(fd, "w", encoding=encoding, newline=newline)) as fh:
        yield fh
        fh.flush()
        os.fsync(fh.fileno())


def _check_at(dfd: int, path: Path) -> None:
    """check_output for the name path.name in the folder dfd."""
    try:
        st = os.lstat(path.name, dir_fd=dfd)
    except FileNotFoundError:
        return
    if stat.S_ISLNK(st.st_mode):
        raise FileRefused(f"{path} is a symbolic link; imubench does not write through links it did not "
                          "create: remove it or choose another output name")
    if not stat.S_ISREG(st.st_mode):
        raise FileRefused(f"{path} is {_kind(st.st_mode)}, not a regular file; choose another output name")


def _atomic_output_portable(path: Path, binary: bool, encoding: str, newline):
    directory = _parent(path)
    _check_components(directory)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=directory)
    try:
        yield from _synced(fd, binary, encoding, newline)
        check_output(path)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write data to path atomically (atomic_output)."""
    with atomic_output(path, binary=True) as fh:
        fh.write(data)
    return Path(path)


def write_text(path: str | os.PathLike, text: str, encoding: str = "utf-8") -> Path:
    """Write text to path atomically (atomic_output)."""
    with atomic_output(path, encoding=encoding) as fh:
        fh.write(text)
    return Path(path)


def open_growing(path: str | os.PathLike, append: bool = True, binary: bool = True, buffering: int = -1,
                 newline: str | None = None, exclusive: bool | None = None):
    """A file that is written as it grows (a capture, a live CSV log): opened relative to its
    folder, which is reached without following a link (open_dir), with O_NOFOLLOW (a symlink
    at path is refused, never written through), and refused unless it is a regular file with
    one link (a FIFO is not waited on; a hard link would grow another file).
    exclusive: the file must not exist yet (O_EXCL); the default for a capture (append):
    an existing capture is refused, never appended to. Otherwise (append=False) an existing
    file is truncated, after the checks."""
    path = check_output(path)
    if exclusive is None:
        exclusive = append
    flags = os.O_WRONLY | os.O_CREAT | _NOFOLLOW | _NOCTTY | _NONBLOCK | getattr(os, "O_CLOEXEC", 0)
    flags |= os.O_EXCL if exclusive else 0
    flags |= os.O_APPEND if append else 0
    dfd = open_dir(_parent(path), create=False) if _OPENAT else None
    try:
        fd = os.open(path.name, flags, 0o666, dir_fd=dfd) if dfd is not None else os.open(path, flags, 0o666)
    except FileExistsError:
        raise FileRefused(f"{path} exists already; a capture is never appended to or replaced: "
                          "choose another name or move the old one away") from None
    except OSError as e:
        if e.errno in (errno.ELOOP, errno.ENXIO):
            check_output(path)       # names the symlink or the FIFO
        raise
    finally:
        if dfd is not None:
            os.close(dfd)
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise FileRefused(f"{path} is {_kind(st.st_mode)}, not a regular file; choose another output name")
        if st.st_nlink > 1:
            raise FileRefused(f"{path} has {st.st_nlink} links (a hard link to another file): writing it would "
                              "change that file too; remove it or choose another output name")
        if not append and not exclusive:
            os.ftruncate(fd, 0)
        if _NONBLOCK:
            os.set_blocking(fd, True)
        if binary:
            return os.fdopen(fd, "ab" if append else "wb", buffering=buffering)
        return os.fdopen(fd, "a" if append else "w", buffering=buffering, encoding="utf-8", newline=newline)
    except BaseException:
        os.close(fd)
        raise


# ------------------------------------------------------------------ inputs
def open_input(path: str | os.PathLike, what: str = "", binary: bool = True, encoding: str = "utf-8",
               errors: str = "strict", newline: str | None = None):
    """path opened for reading, refused (FileRefused) unless it is a regular file: a FIFO is
    opened without blocking and refused, a device or a directory too. `what` names the file in
    the message ("the session file")."""
    path = Path(path)
    label = f"{what} {path}" if what else str(path)
    try:
        fd = os.open(path, os.O_RDONLY | _NONBLOCK | _NOCTTY)
    except IsADirectoryError:
        raise FileRefused(f"{label} is a directory; give a regular file") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise FileRefused(f"{label} is {_kind(st.st_mode)}; give a regular file")
        if _NONBLOCK:
            os.set_blocking(fd, True)
        if binary:
            return os.fdopen(fd, "rb")
        return os.fdopen(fd, "r", encoding=encoding, errors=errors, newline=newline)
    except BaseException:
        os.close(fd)
        raise


def check_input(path: str | os.PathLike, what: str = "") -> Path:
    """path, after checking that it is a regular file (open_input, closed again)."""
    with open_input(path, what):
        pass
    return Path(path)


def read_bytes(path: str | os.PathLike, limit: int, what: str = "") -> bytes:
    """The content of the regular file at path, refused when larger than limit bytes (checked
    before reading, and again while reading: a file that grows is not read without end)."""
    path = Path(path)
    label = f"{what} {path}" if what else str(path)
    with open_input(path, what) as fh:
        size = os.fstat(fh.fileno()).st_size
        if size > limit:
            raise FileRefused(f"{label} is {size / MiB:.1f} MiB, more than the limit of {limit / MiB:.0f} MiB "
                              f"for this kind of file; is it the right file?")
        data = fh.read(limit + 1)
    if len(data) > limit:
        raise FileRefused(f"{label} grew past the limit of {limit / MiB:.0f} MiB while being read")
    return data


def read_text(path: str | os.PathLike, limit: int = MAX_JSON_BYTES, what: str = "", encoding: str = "utf-8",
              errors: str = "strict") -> str:
    """read_bytes, decoded (a decoding error is a FileRefused naming the file)."""
    data = read_bytes(path, limit, what)
    try:
        return data.decode(encoding, errors)
    except UnicodeDecodeError as e:
        label = f"{what} {path}" if what else str(path)
        raise FileRefused(f"{label} is not {encoding} text (byte {e.start}); is it the right file?") from None


def bounded_lines(fh, max_chars: int = MAX_LINE_CHARS, name: str = "") -> Iterator[str]:
    """The lines of a text file object, each read with a bound: a line longer than max_chars
    (a binary file, /dev/zero renamed .csv) is a FileRefused, not gigabytes of memory."""
    lineno = 0
    while True:
        line = fh.readline(max_chars + 1)
        if not line:
            return
        lineno += 1
        if len(line) > max_chars and not line.endswith("\n"):
            raise FileRefused(f"{name or 'the file'}: line {lineno} is longer than the limit of "
                              f"{max_chars} characters; is it a text file of this format?")
        yield line


def tree_digest(directory: str | os.PathLike, pattern: str = "*.bin") -> tuple[str | None, list[Path]]:
    """One SHA-256 over every file matching pattern under directory (recursively), in path order,
    each as its path relative to directory, a NUL byte and its bytes (read with open_input, a
    chunk at a time): "these runs wrote the same files, byte for byte" in one comparison (the
    determinism checks: bench/determinism.py, tests/device/test_lockstep.py). Returns (the hex
    digest, or None when nothing matched; the files)."""
    import hashlib
    d = Path(directory)
    files = sorted(d.rglob(pattern))
    if not files:
        return None, []
    h = hashlib.sha256()
    for f in files:
        h.update(f.relative_to(d).as_posix().encode() + b"\0")
        with open_input(f) as fh:
            for chunk in iter(lambda: fh.read(1 << 20), b""):
                h.update(chunk)
    return h.hexdigest(), files
