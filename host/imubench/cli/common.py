"""What every subcommand shares: the parser class, the common options, argument types that
check values on the host before anything is sent, and the one error convention.

The convention (docs/architecture.md, "The command line"): a user mistake or a problem of
the environment prints ONE line on stderr,

    imubench CMD: error: what happened; what to do

and exits 2 (usage: the arguments are wrong), 1 (the command failed) or 130 (interrupted by
Ctrl-C). No traceback reaches the user unless `--debug` is given (or IMUBENCH_DEBUG=1).
"""
from __future__ import annotations

import argparse
import errno
import os
import sys
from pathlib import Path

from imubench.device.link import DEFAULT_BAUD, PORT_ENV
from imubench.text import one_line
from imubench.wire.protocol_gen import STREAM_RATES_HZ

EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130


class CommandError(Exception):
    """A failure the command explains itself: `what` happened; `todo` says what to do.
    Raise it from a subcommand; main() prints it in the one-line form."""

    def __init__(self, what: str, todo: str = "", code: int = EXIT_FAILED):
        super().__init__(what)
        self.what, self.todo, self.code = what, todo, code


class UsageError(CommandError):
    """The arguments are wrong (exit 2), found after parsing (e.g. two options that exclude each other)."""

    def __init__(self, what: str, todo: str = ""):
        super().__init__(what, todo, EXIT_USAGE)


# ------------------------------------------------------------------ the parser
class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows every option's default: "(default: X)" after its help, unless the help already
    says it or there is none to show (a flag, an empty list)."""

    def _get_help_string(self, action):
        h = action.help or ""
        d = action.default
        if "%(default)" in h or "default:" in h or d is None or d is False or d is argparse.SUPPRESS \
                or (isinstance(d, (list, str)) and not d):
            return h
        if action.option_strings or action.nargs in (argparse.OPTIONAL, argparse.ZERO_OR_MORE):
            return h + " (default: %(default)s)"
        return h


class Parser(argparse.ArgumentParser):
    """argparse with the one-line error convention: `imubench CMD: error: ...; see ... --help`."""

    def __init__(self, *a, **kw):
        kw.setdefault("formatter_class", HelpFormatter)
        super().__init__(*a, **kw)

    def error(self, message: str):  # noqa: D401 - argparse's hook
        sys.stderr.write(one_line(f"{self.prog}: error: {message}; see '{self.prog} --help'") + "\n")
        sys.exit(EXIT_USAGE)


# ------------------------------------------------------------------ shared options
class _PortsAction(argparse.Action):
    """--port given once or more: `port` is the first URL (as for every command), `ports` all of them."""

    def __call__(self, parser, ns, value, option_string=None):
        ports = list(getattr(ns, "ports", None) or [])
        if value in ports:
            raise argparse.ArgumentError(self, f"{value} is given twice: one board per port")
        ports.append(value)
        ns.ports = ports
        if getattr(ns, "port", None) is None:
            ns.port = value


def add_port(p: argparse.ArgumentParser, many: bool = False) -> None:
    """--port and --baud, the same in every command that talks to a device. With many=True
    --port may be repeated (several boards on one fixture): args.port is the first, args.ports
    the list (None when not given)."""
    p.add_argument("--port", metavar="URL", **({"action": _PortsAction} if many else {}),
                   help=f"pyserial URL of the device: /dev/ttyUSB0, socket://HOST:PORT, rfc2217://HOST:PORT "
                        f"(default: the environment variable {PORT_ENV})"
                        + ("; repeat it for several boards on one fixture (one station session)" if many else ""))
    if many:
        p.set_defaults(ports=None)
    p.add_argument("--baud", type=baud, default=DEFAULT_BAUD, help="baud rate of a real UART")


def add_sim(p: argparse.ArgumentParser, what: str, speed: float | None = 20.0, lockstep_speed: float = 0.0) -> None:
    """--sim, --sim-seed, --sim-speed, --sim-clock: run on a virtual device started (and removed)
    by the command. --sim-speed when not given (resolve_sim_speed): `lockstep_speed` on the
    lockstep clock (0: no ceiling, the device runs as fast as the host takes it), `speed` on the
    real-time clock (None: the command chooses)."""
    p.add_argument("--sim", action="store_true", help=what)
    p.add_argument("--sim-seed", type=int, default=1, metavar="N", help="random seed of the virtual device's truth")
    ceiling = "none" if not lockstep_speed else f"{lockstep_speed:g}"
    pace = "" if speed is None else f" (default {speed:g})"
    p.add_argument("--sim-speed", type=non_negative_float, default=None, metavar="X",
                   help=f"virtual device time per wall-clock time (1 = real time). On the lockstep clock a "
                        f"ceiling (0 = none; default {ceiling}); on the real-time clock the pace{pace}")
    p.set_defaults(sim_speed_defaults=(lockstep_speed, speed))
    p.add_argument("--sim-clock", choices=("lockstep", "realtime"), default=None,
                   help="lockstep (the default): the virtual device's time moves only as the host takes what "
                        "it sends, nothing is dropped and the same seed gives the same session on any machine, "
                        "the host build and the ARM images alike; realtime: it runs against the wall clock and "
                        "drops what a slow host does not read, as a real board does (docs/simulator.md)")
    add_target(p)


def resolve_sim_speed(a: argparse.Namespace) -> None:
    """Fill in --sim-speed when it was not given (add_sim) and note whether it was
    (a.sim_speed_given); refuse 0 on the real-time clock. Safe to call twice."""
    if not hasattr(a, "sim_speed_defaults") or getattr(a, "_sim_speed_resolved", False):
        return
    a._sim_speed_resolved = True
    lockstep_default, realtime_default = a.sim_speed_defaults
    realtime = getattr(a, "sim_clock", None) == "realtime"
    a.sim_speed_given = a.sim_speed is not None
    if a.sim_speed is None:
        a.sim_speed = realtime_default if realtime else lockstep_default
    elif realtime and a.sim_speed == 0:
        raise UsageError("--sim-speed 0 (no ceiling) needs the lockstep clock",
                         "give a pace for --sim-clock realtime, e.g. --sim-speed 20")


def speed_text(speed: float, clock: str | None) -> str:
    """How a virtual device's --sim-speed reads in a header line."""
    if clock == "realtime":
        return f"speed {speed:g} (real-time clock)"
    return "lockstep clock, no speed ceiling" if not speed else f"lockstep clock, speed ceiling {speed:g}"


def image_help(what: str = "<board>") -> tuple[str, str, str]:
    """(what `flash` does with the STM32 images, the default image's path, what --no-build does),
    worded for the user's install: a wheel carries its images (nothing is built), a checkout
    builds them with `make firmware`."""
    from imubench.device import artifacts
    if artifacts.installed():
        d = artifacts.DATA / "firmware" / what
        return ("Flash the STM32 firmware image that came with this installed package",
                f"{d}/imubench.elf|.bin|.hex",
                "accepted for scripts; nothing is built (the package's images were built with it)")
    return ("Build (make firmware) and flash the STM32 firmware", f"build/arm/{what}/imubench.elf|.bin|.hex",
            "do not run `make firmware` first")


def add_target(p: argparse.ArgumentParser) -> None:
    """--target: what runs the virtual device's firmware (imubench.device.sim.TARGETS)."""
    p.add_argument("--target", choices=("host", "f103", "f4"), default="host",
                   help="host: the firmware core built for Linux (fast); f103 / f4: the exact STM32 image "
                        "under the ARM emulator against the same sensor models (docs/firmware.md)")


# ------------------------------------------------------------------ argument types
def stream_rate(s: str) -> int:
    """A sample rate the protocol definition allows (protocol/imubench.toml, stream_rates_hz)."""
    allowed = ", ".join(str(r) for r in sorted(STREAM_RATES_HZ))
    try:
        r = int(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{s!r} is not a rate in Hz (allowed: {allowed})") from None
    if r not in STREAM_RATES_HZ:
        raise argparse.ArgumentTypeError(f"{r} Hz is not a stream rate of the protocol (allowed: {allowed})")
    return r


def baud(s: str) -> int:
    try:
        b = int(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{s!r} is not a baud rate (e.g. 2000000, 921600, 115200)") from None
    if not 1200 <= b <= 20_000_000:
        raise argparse.ArgumentTypeError(f"{b} is not a plausible baud rate (1200 to 20000000)")
    return b


def _number(s: str, allow_zero: bool) -> float:
    try:
        v = float(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{s!r} is not a number") from None
    if not (v >= 0 if allow_zero else v > 0) or v == float("inf"):
        raise argparse.ArgumentTypeError(f"{s} must be {'zero or ' if allow_zero else ''}a positive number")
    return v


def positive_float(s: str) -> float:
    return _number(s, allow_zero=False)


def non_negative_float(s: str) -> float:
    return _number(s, allow_zero=True)


def existing_file(s: str) -> Path:
    """A regular file that exists (not a directory)."""
    p = Path(s)
    if p.is_dir():
        raise argparse.ArgumentTypeError(f"{s} is a directory, not a file")
    if not p.exists():
        raise argparse.ArgumentTypeError(f"{s}: no such file")
    return p


def existing_dir(s: str) -> Path:
    p = Path(s)
    if not p.exists():
        raise argparse.ArgumentTypeError(f"{s}: no such directory")
    if not p.is_dir():
        raise argparse.ArgumentTypeError(f"{s} is a file, not a directory")
    return p


def new_file(s: str) -> Path:
    """A file to write: not a directory, in a directory that exists."""
    p = Path(s)
    if p.is_dir():
        raise argparse.ArgumentTypeError(f"{s} is a directory: give a file name")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise argparse.ArgumentTypeError(f"{parent} does not exist: create it first")
    return p


def out_dir(s: str) -> Path:
    """A directory to write into (created when missing), not a file."""
    p = Path(s)
    if p.exists() and not p.is_dir():
        raise argparse.ArgumentTypeError(f"{s} is a file: give a directory")
    return p


# ------------------------------------------------------------------ explaining failures
def explain(e: BaseException, cmd: str) -> tuple[str, int]:
    """The one line (without the `imubench CMD: error: ` prefix) and the exit code for an
    exception that escaped a subcommand. Unknown exceptions are bugs: they say so.
    Classes are recognised by name along the MRO, so that explaining an error imports nothing
    (a failing `imubench info` must not first load scipy)."""
    names = [c.__name__ for c in type(e).__mro__]

    def line(what, todo: str = "") -> str:
        what = " ".join(str(what).split()).rstrip(".")
        return f"{what}; {todo}" if todo and todo not in what else what

    def kind(*candidates: str) -> bool:
        return any(n in names for n in candidates)

    if isinstance(e, CommandError):
        return line(e.what, e.todo), e.code
    if kind("NoPort"):
        return line(e), EXIT_USAGE
    if kind("CaptureError"):
        if getattr(e, "errno", None) == errno.ENOSPC:
            return f"{e.filename}: no space left on the disk; free some space (everything written so far is kept)", \
                EXIT_FAILED
        return line(e, "check the disk (everything written so far is kept)"), EXIT_FAILED
    if kind("ProtocolVersionError"):
        return str(e), EXIT_FAILED
    if kind("NewerFirmware"):
        return line(e, "update imubench (pip install -U imubench) to a version that knows this firmware"), EXIT_FAILED
    if kind("LinkTimeout"):
        return line(e, "check the power, the cable, --baud and that the board runs imubench firmware "
                       "(imubench flash; imubench info)"), EXIT_FAILED
    if kind("LinkError"):
        return line(e, "check the URL (a device path like /dev/ttyUSB0, or socket://HOST:PORT), that the "
                       "device is plugged in and that no other program holds the port"), EXIT_FAILED
    if kind("DeviceError"):
        return line(e, "imubench info shows the device's state; protocol/MESSAGES.md lists the error codes"), \
            EXIT_FAILED
    if kind("NotObservable"):
        return line(f"the calibration cannot be observed: {e}",
                    "add attitudes (docs/calibration.md) or choose another --method"), EXIT_FAILED
    if kind("CalibrationError"):
        return line(f"calibration failed: {e}", "see docs/calibration.md"), EXIT_FAILED
    if kind("ClosureError"):
        return line(f"closure check not possible: {e}", "see docs/closure.md"), EXIT_FAILED
    if kind("HistoryError"):
        return line(e, "imubench history --db PATH lists the devices a database holds"), EXIT_FAILED
    if kind("InvalidParams"):
        return line(f"invalid parameters: {e}", "nothing was written"), EXIT_FAILED
    if kind("SimError", "QemuError", "ArtifactError"):
        from imubench.device.artifacts import installed
        return line(e, "rerun with --debug" if installed() else
                    "run `make sim` / `make firmware` in the source checkout, or rerun with --debug"), EXIT_FAILED
    if kind("FlashError"):
        return line(e, "see docs/firmware.md, Flashing"), getattr(e, "code", EXIT_FAILED)
    if kind("ImubenchError"):
        return line(e), EXIT_FAILED
    if isinstance(e, OSError):
        name = f"{e.filename}: " if getattr(e, "filename", None) else ""
        if e.errno == errno.ENOSPC:
            return f"{name}no space left on the device; free some space (everything written so far is kept)", \
                EXIT_FAILED
        if isinstance(e, IsADirectoryError):
            return f"{name}is a directory; give a file", EXIT_FAILED
        if isinstance(e, NotADirectoryError):
            return f"{name}is not a directory; give a directory", EXIT_FAILED
        if isinstance(e, FileNotFoundError):
            return f"{name}no such file or directory; check the path", EXIT_FAILED
        if isinstance(e, FileExistsError):
            return f"{name}exists already; choose another name (nothing was overwritten)", EXIT_FAILED
        if isinstance(e, PermissionError):
            return f"{name}permission denied; choose a place you may write to, or fix its permissions", \
                EXIT_FAILED
        return line(f"{name}{e.strerror or e}", "check the file or device named"), EXIT_FAILED
    return (f"internal error ({type(e).__name__}: {' '.join(str(e).split())}); this is a bug in imubench: "
            "rerun with --debug and report the traceback"), EXIT_FAILED


def debug_enabled(args) -> bool:
    return bool(getattr(args, "debug", False)) or os.environ.get("IMUBENCH_DEBUG", "") not in ("", "0")
