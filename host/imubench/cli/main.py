"""The one `imubench` command line: every subcommand is registered here, and every one of them
fails the same way (imubench.cli.common: one line, exit 2 / 1 / 130, no traceback without
--debug).

Each subcommand lives in its own module of this package with two functions:
`register(subparsers)` adds its parser (and `set_defaults(run=run)`), and `run(args) -> int`
is a thin adapter from the arguments to a procedure (imubench.procedures) or a device command.
A subcommand may set `args.on_interrupt` (a string or a function returning one) to tell the
user, after Ctrl-C, how to continue.
"""
from __future__ import annotations

import argparse
import signal
import sys

from imubench.cli import (
    allan,
    attitude,
    calibrate,
    closure,
    demo,
    flash,
    history,
    report,
    station,
    stream,
    thermal,
    virtual,
)
from imubench.cli.common import EXIT_INTERRUPTED, Parser, debug_enabled, explain, resolve_sim_speed
from imubench.text import guard_terminal, one_line

# the order of `imubench --help`: a session first, then what follows it, then the tools
MODULES = (calibrate, station, history, report, closure, allan, attitude, thermal, stream, virtual, flash, demo)


def build_parser() -> argparse.ArgumentParser:
    from imubench.device.artifacts import installed
    where = ("README.md lists the commands; docs/ has the methods (both in the sdist, imubench-<version>.tar.gz, "
             "and the source repository: the docs/NAME.md the help texts name)." if installed() else
             "README.md lists the commands; docs/ has the methods.")
    ap = Parser(prog="imubench",
                description="Hardware-in-the-loop bench for calibrating MEMS IMUs (ADXL355 + ADXRS450 on an STM32).\n"
                            "Every command that talks to a device takes --port URL (default: $IMUBENCH_PORT).\n"
                            + where)
    ap.add_argument("--version", action=_Version, nargs=0,
                    help="the package version, the source revision and the firmware images' versions")
    ap.add_argument("--debug", action="store_true",
                    help="show the full traceback of an error (also: IMUBENCH_DEBUG=1)")
    sub = ap.add_subparsers(dest="cmd", required=True, metavar="COMMAND", parser_class=Parser)
    for m in MODULES:
        m.register(sub)
    # every subcommand also takes --debug after its name
    for p in sub.choices.values():
        p.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                       help="show the full traceback of an error (also: IMUBENCH_DEBUG=1)")
    return ap


class _Version(argparse.Action):
    """--version: computed when asked (the checkout's revision needs git), then exit 0."""

    def __call__(self, parser, namespace, values, option_string=None):
        from imubench.device.artifacts import version_text
        try:
            text = version_text()
        except Exception as e:  # noqa: BLE001 - a damaged install still says its version
            from imubench import __version__
            text = f"imubench {__version__} (compiled parts unreadable: {e})"
        print(text, flush=True)
        parser.exit(0)


def _interrupted(e: BaseException) -> bool:
    """A failure that is a Ctrl-C in disguise: a KeyboardInterrupt in its chain, or the
    ImportError a compiled module raises when the interrupt arrives while it initialises."""
    seen = 0
    while e is not None and seen < 10:
        if isinstance(e, KeyboardInterrupt) or (isinstance(e, ImportError) and str(e) == "initialization failed"):
            return True
        e, seen = e.__cause__ or e.__context__, seen + 1
    return False


def main(argv=None) -> int:
    guard_terminal(sys)              # no escape sequence from a name or a file acts on a terminal
    try:
        args = build_parser().parse_args(sys.argv[1:] if argv is None else list(argv))
    except SystemExit as e:          # --help, --version (0) or a usage error (2, one line printed)
        return e.code if isinstance(e.code, int) else 0
    except KeyboardInterrupt:        # Ctrl-C while the commands were still being imported
        _say("imubench: interrupted")
        return EXIT_INTERRUPTED
    prefix = f"imubench {args.cmd}: error: "
    try:
        resolve_sim_speed(args)
        return int(args.run(args) or 0)
    except KeyboardInterrupt:
        if debug_enabled(args):
            raise
        hint = getattr(args, "on_interrupt", None)
        hint = hint() if callable(hint) else hint
        _say(prefix + "interrupted" + (f"; {hint}" if hint else ""))
        return EXIT_INTERRUPTED
    except SystemExit:
        raise
    except BrokenPipeError:          # `imubench decode FILE | head`: the reader went away
        sys.stderr.close()
        return 0
    except Exception as e:  # noqa: BLE001 - the one place every failure is explained
        if debug_enabled(args):
            raise
        if _interrupted(e):          # Ctrl-C that landed inside an import of a compiled module
            hint = getattr(args, "on_interrupt", None)
            hint = hint() if callable(hint) else hint
            _say(prefix + "interrupted" + (f"; {hint}" if hint else ""))
            return EXIT_INTERRUPTED
        line, code = explain(e, args.cmd)
        _say(prefix + line)
        return code


def entry() -> None:
    """The `imubench` executable (and `python -m imubench`): main(), then exit with its code.

    After Ctrl-C the exit must be 130 every time. CPython records a KeyboardInterrupt that
    passes through a string exec() (scipy and numpy run some on import, and our imports are
    lazy) as "unhandled", even when main() then handles it, and at exit kills the process
    with SIGINT instead of returning the code (a shell sees 130, a parent process -2). So an
    interrupted run flushes, runs the exit handlers itself and leaves with os._exit(130)."""
    code = main()
    if code == EXIT_INTERRUPTED:
        signal.signal(signal.SIGINT, signal.SIG_IGN)    # a second Ctrl-C while leaving: no traceback
        import atexit
        import os
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        atexit._run_exitfuncs()
        os._exit(code)
    sys.exit(code)


def _say(line: str) -> None:
    try:
        sys.stdout.flush()
    except (OSError, ValueError):
        pass
    print(one_line(line), file=sys.stderr, flush=True)       # free text (a file name, a reason) acts on no terminal


if __name__ == "__main__":
    entry()
