"""Numbers as a person reads them: every estimate to the precision its uncertainty allows.

The rule (JCGM 100:2008, "Evaluation of measurement data — Guide to the expression of
uncertainty in measurement" (GUM), 7.2.6): the standard uncertainty is given to two
significant digits, and the value is rounded to the same decimal place.

    pm(3320.3, 25862.3, "ppm")   ->  "+3000 ± 26000 ppm"
    pm(-8.218282, 0.00625, "mg") ->  "-8.2183 ± 0.0063 mg"
    pm(1.0, 0.0)                 ->  "not estimated"     (a parameter the model holds fixed)

Used by every table and report that shows an estimate (results.calibration, results.history,
results.report), so the console, the history and the HTML agree digit for digit.
"""
from __future__ import annotations

import math

NOT_ESTIMATED = "not estimated"


def _finite(x) -> float | None:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def decimals_for(sigma: float, digits: int = 2) -> int:
    """Decimal places that leave `digits` significant digits in sigma (may be negative:
    -3 rounds to thousands)."""
    return digits - 1 - int(math.floor(math.log10(abs(sigma))))


def round_pair(value: float, sigma: float, digits: int = 2) -> tuple[str, str]:
    """(value, sigma) as text, sigma with `digits` significant digits and the value to the
    same decimal place; the value signed."""
    d = decimals_for(sigma, digits)
    rounded = round(abs(sigma), d)
    if rounded > 0:
        d = decimals_for(rounded, digits)     # 0.0995 rounds to 0.10: two digits there

    def fmt(x: float, sign: str) -> str:
        if d >= 0:
            return f"{round(x, d):{sign}.{d}f}"
        q = 10.0 ** -d
        return f"{round(x / q) * q:{sign}.0f}"

    v, s = fmt(value, "+"), fmt(abs(sigma), "")
    if v.startswith("-") and float(v) == 0.0:
        v = "+" + v[1:]                         # no "-0.000"
    return v, s


def pm(value, sigma, unit: str = "", scale: float = 1.0, digits: int = 2, fixed_text: str = NOT_ESTIMATED) -> str:
    """'value ± sigma unit' rounded to sigma's precision; `fixed_text` where sigma is 0 or
    missing (the model fixes that parameter, or nothing estimated it); '–' with no value."""
    v = _finite(value)
    s = _finite(sigma)
    if v is None:
        return "–"
    if s is None or s == 0.0:
        return fixed_text
    vt, st = round_pair(v * scale, s * scale, digits)
    return f"{vt} ± {st}" + (f" {unit}" if unit else "")


def value(v, sigma=None, unit: str = "", scale: float = 1.0, digits: int = 2) -> str:
    """A value alone, to the precision of sigma (given) or to `digits` significant digits."""
    x = _finite(v)
    if x is None:
        return "–"
    s = _finite(sigma)
    if s:
        vt, _ = round_pair(x * scale, s * scale, digits)
    else:
        vt = f"{x * scale:.{digits}g}"
    return vt + (f" {unit}" if unit else "")


def significant(v, digits: int = 3, unit: str = "") -> str:
    """A measured figure with no uncertainty of its own (a limit check's value) to `digits`
    significant digits, trailing zeros kept: significant(3.0) -> '3.00', 0.01234 -> '0.0123'."""
    x = _finite(v)
    if x is None:
        return "–"
    if x == 0.0:
        t = f"{0.0:.{digits - 1}f}"
    else:
        d = digits - 1 - int(math.floor(math.log10(abs(x))))
        t = f"{round(x, d):.{max(d, 0)}f}"
    return t + (f" {unit}" if unit else "")
