"""Free text made safe for where it goes (the bottom layer: imports nothing).

Free text (a recording's file name, a note, a station or operator name from a database, a
string a device sends, an exception's message) may hold anything: line breaks that add lines
to a parameter file, escape sequences that rewrite a terminal, bytes XML 1.0 cannot carry.
Each destination has one function here and every writer uses it:

- ``printable``  a terminal (and any log a person reads): control characters (C0, DEL, C1),
                 line and paragraph separators and the bidirectional overrides become visible
                 escapes (``\\x1b``, ``\\u202e``); line breaks kept only when asked;
- ``one_line``   a field that must stay on its line (a comment in a parameter file, one line
                 of a terminal): ``printable`` with line breaks escaped too;
- ``comment``    a comment line in another tool's file (`# ...` in YAML, OpenCV FileStorage, a
                 QGroundControl or MAVProxy parameter file): ``one_line`` after the marker, so that
                 no quoted name can end the comment and start a line the tool reads;
- ``token``      a name quoted as a value (imu_utils' `name:`, a ROS topic): only letters,
                 digits and ``_ . / ~ -``, every other character ``_``;
- ``xml_text``   XML 1.0 character data or attribute values (JUnit): characters XML cannot
                 carry at all are dropped (escaping <, &, quotes is the serialiser's job).
"""
from __future__ import annotations

import re

# C0 controls but tab and newline, DEL, C1, the Unicode line/paragraph separators and the
# bidirectional embeddings/overrides/isolates (they reorder what a reader sees)
_UNSAFE = "\x00-\x08\x0b-\x1f\x7f-\x9f\u2028\u2029\u202a-\u202e\u2066-\u2069\u200e\u200f\u061c"
_UNSAFE_KEEP_LINES = re.compile(f"[{_UNSAFE}]")
_UNSAFE_ONE_LINE = re.compile(f"[{_UNSAFE}\t\n]")
_XML_INVALID = re.compile("[\x00-\x08\x0b\x0c\x0e-\x1f\ufffe\uffff\ud800-\udfff]")


def _escape(m: re.Match) -> str:
    c = m.group(0)
    if c == "\t":
        return "\\t"
    if c == "\n":
        return "\\n"
    if c == "\r":
        return "\\r"
    return f"\\x{ord(c):02x}" if ord(c) < 0x100 else f"\\u{ord(c):04x}"


def printable(text, keep_newlines: bool = True) -> str:
    """str(text) with every character that would act on a terminal instead of showing
    (an escape sequence, a carriage return, a backspace, a bidi override) written as a
    visible escape; newlines and tabs kept unless keep_newlines is False (then one_line)."""
    s = str(text)
    return (_UNSAFE_KEEP_LINES if keep_newlines else _UNSAFE_ONE_LINE).sub(_escape, s)


def one_line(text) -> str:
    """printable(text) on one line: newlines and tabs escaped too (a comment, a field)."""
    return printable(text, keep_newlines=False)


def comment(text, marker: str = "#") -> str:
    """One comment line in another tool's file: marker, a space, one_line(text). Every line break
    those tools know (LF, CR, VT, FF, NEL, U+2028/9) and every control character is escaped."""
    return f"{marker} {one_line(text)}"


_NOT_TOKEN = re.compile(r"[^A-Za-z0-9_./~-]")


def token(text, default: str = "imu") -> str:
    """text as a bare value no parser reads as syntax: letters, digits and _ . / ~ - kept,
    anything else '_' (a YAML scalar, a ROS name); default when nothing is left."""
    return _NOT_TOKEN.sub("_", str(text)) or default


def shell_word(text) -> str:
    """text as one word a POSIX shell (bash, zsh, ksh) reads back as text, shown safely on a
    terminal: shlex.quote when it is printable; else ANSI-C quoting ($'...') with every
    control character, bidi override or line separator written as an escape the shell decodes."""
    import shlex
    s = str(text)
    if not _UNSAFE_ONE_LINE.search(s):
        return shlex.quote(s)
    body = s.replace("\\", "\\\\").replace("'", "\\'")
    return "$'" + _UNSAFE_ONE_LINE.sub(_escape, body) + "'"


def xml_text(text) -> str:
    """str(text) without the characters XML 1.0 cannot hold (most C0 controls, U+FFFE, U+FFFF,
    lone surrogates), so that any serialiser's output stays well-formed."""
    return _XML_INVALID.sub("", str(text))


class SafeTerminal:
    """A terminal stream (sys.stdout, sys.stderr) whose every write passes through printable:
    the last guard, behind the one_line/printable calls of each command, so that no text from
    a user, a file or a device that a message forgot to escape rewrites the operator's
    terminal. Installed only when the stream is a terminal (guard_terminal); a pipe or a file
    gets the bytes a command writes (a CSV's CR LF stays)."""

    def __init__(self, stream):
        self._stream = stream

    def write(self, text: str) -> int:
        self._stream.write(printable(text))
        return len(text)

    def writelines(self, lines) -> None:
        for line in lines:
            self.write(line)

    def __getattr__(self, name):
        return getattr(self._stream, name)


def guard_terminal(sys_module) -> None:
    """sys.stdout and sys.stderr wrapped in SafeTerminal where they are terminals."""
    for name in ("stdout", "stderr"):
        stream = getattr(sys_module, name, None)
        try:
            tty = stream is not None and not isinstance(stream, SafeTerminal) and stream.isatty()
        except (AttributeError, ValueError, OSError):
            tty = False
        if tty:
            setattr(sys_module, name, SafeTerminal(stream))
