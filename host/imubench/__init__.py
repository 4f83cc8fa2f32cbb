"""imubench: a hardware-in-the-loop bench for calibrating MEMS IMUs (docs/architecture.md)."""


def __getattr__(name: str):
    """__version__ on first use (PEP 562): importlib.metadata and its search of every installed
    distribution are not paid by each command's start, only where the version is printed."""
    if name != "__version__":
        raise AttributeError(f"module 'imubench' has no attribute {name!r}")
    from importlib.metadata import PackageNotFoundError, version
    try:
        v = version("imubench")
    except PackageNotFoundError:       # running from a source tree that is not installed
        v = "0+unknown"
    globals()["__version__"] = v
    return v
