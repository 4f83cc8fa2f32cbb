"""imubench: a hardware-in-the-loop bench for calibrating MEMS IMUs (docs/architecture.md)."""
try:
    from importlib.metadata import PackageNotFoundError, version

    __version__ = version("imubench")
except PackageNotFoundError:       # running from a source tree that is not installed
    __version__ = "0+unknown"
