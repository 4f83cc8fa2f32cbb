"""The progress bar of a read (every reader of imubench.recordings)."""
from __future__ import annotations


def progress(total: int, desc: str, unit: str = "B"):
    """A tqdm bar (as the rest of the tool) on stderr, shown only when the work lasts over a second
    and stderr is a terminal: bytes (or samples) done and the time left."""
    from tqdm import tqdm
    return tqdm(total=total, desc=desc, unit=unit, unit_scale=True, unit_divisor=1024 if unit == "B" else 1000,
                delay=1.0, leave=False, disable=None, dynamic_ncols=True)
