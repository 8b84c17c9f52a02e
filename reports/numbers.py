"""Numbers as a reader sees them: a value with its uncertainty, digits set by the uncertainty.

Every number in the report and the terminal summary goes through :func:`fmt_pm` (value ±
standard error) or :func:`fmt_num` (a number without an error). No function here returns the
``repr`` of a Python object: ``None`` becomes "—" (or the caller's word), booleans "yes"/"no",
non-finite errors "not determined" (``docs/reports.md#numbers``).

Examples
--------
>>> fmt_pm(0.790123, 0.000047)
'0.790123 ± 0.000047'
>>> fmt_pm(30.001057015731455, 0.52)
'30.00 ± 0.52'
>>> fmt_pm(1234.5, 260.0)
'1230 ± 260'
>>> fmt_pm(0.5, float("inf"))
'0.5 (not determined)'
>>> fmt_pm(0.5, None)
'0.5'
>>> fmt_num(0.000123456)
'0.000123'
"""

from __future__ import annotations

import math
import re
from html.parser import HTMLParser
from typing import Iterable

__all__ = ["fmt_pm", "fmt_num", "fmt_rgb_pm", "fmt_rgb", "fmt_band", "REPR_PATTERNS",
           "find_reprs", "visible_text"]

#: Significant digits of the standard error (the value is rounded to the same decimal place).
ERROR_DIGITS = 2


def _finite(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def fmt_num(v, digits: int = 3, missing: str = "—") -> str:
    """Format a number without an uncertainty, ``digits`` significant digits; words for the rest.

    Integers are written in full; ``None`` as ``missing``; ``inf`` as "∞"; ``nan`` as
    ``missing``; booleans as "yes"/"no"; anything else (a string) as is.
    """
    if v is None:
        return missing
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return missing
        if math.isinf(v):
            return "∞" if v > 0 else "−∞"
        if v == 0:
            return "0"
        return f"{v:.{digits}g}"
    return str(v)


def fmt_pm(v, e, missing: str = "—") -> str:
    """``value ± error`` with the error to :data:`ERROR_DIGITS` significant digits.

    The value is rounded to the error's last digit; an exponent common to both is factored out
    when either is very large or small (``(1.23 ± 0.04)e-05``). A non-finite error means the
    data do not determine the value (written "not determined"); a missing error (a given
    value, a MAP estimate without one) leaves the value alone with 4 significant digits.
    """
    if not _finite(v):
        return fmt_num(v, missing=missing)
    if e is None or isinstance(e, bool):
        return fmt_num(v, 4, missing)
    if not isinstance(e, (int, float)) or math.isnan(e):
        return fmt_num(v, 4, missing)
    if math.isinf(e):
        return f"{fmt_num(v, 4, missing)} (not determined)"
    e = abs(float(e))
    v = float(v)
    if e == 0:
        return f"{fmt_num(v, 6)} ± 0"
    exp_e = math.floor(math.log10(e))
    decimals = ERROR_DIGITS - 1 - exp_e  # decimal places that keep ERROR_DIGITS of the error
    big = max(abs(v), e)
    exp_big = math.floor(math.log10(big)) if big > 0 else 0
    if exp_big >= 5 or exp_big <= -5:  # factor out a common power of ten
        s = 10.0 ** exp_big
        d = max(decimals + exp_big, 0)
        return f"({v / s:.{d}f} ± {e / s:.{d}f})e{exp_big:+03d}"
    if decimals <= 0:
        q = 10.0 ** (-decimals)
        return f"{round(v / q) * q:.0f} ± {round(e / q) * q:.0f}"
    return f"{v:.{decimals}f} ± {e:.{decimals}f}"


def _seq(x) -> list:
    if x is None:
        return []
    if isinstance(x, (int, float)):
        return [x]
    return list(x)


def fmt_rgb_pm(values, errors=None, names: str = "RGB") -> str:
    """Per channel ``R 0.79 ± 0.01, G …``; a single value is written without a channel name."""
    v = _seq(values)
    e = _seq(errors)
    e = e + [None] * (len(v) - len(e))
    if len(v) == 1:
        return fmt_pm(v[0], e[0])
    if len(v) > len(names):  # not per channel (a per-band list): index: value
        return ", ".join(f"{i}: {fmt_pm(a, b)}" for i, (a, b) in enumerate(zip(v, e)))
    return ", ".join(f"{names[i]} {fmt_pm(a, b)}" for i, (a, b) in enumerate(zip(v, e)))


def fmt_rgb(values, digits: int = 3) -> str:
    """Per channel values without errors (``R 0.5, G 0.5, B 0.5``); one value alone."""
    v = _seq(values)
    if len(v) == 1:
        return fmt_num(v[0], digits)
    if len(v) > 3:
        return ", ".join(f"{i}: {fmt_num(x, digits)}" for i, x in enumerate(v))
    return ", ".join(f"{'RGB'[i]} {fmt_num(x, digits)}" for i, x in enumerate(v))


def fmt_band(l, none_word: str = "none up to lmax") -> str:
    """Format a band index, or ``none_word`` when there is none."""
    if l is None or (isinstance(l, float) and not math.isfinite(l)):
        return none_word
    return str(int(l))


#: What must never reach a reader: Python reprs of ``None``/booleans, nested lists, dicts, NaN
#: shown as a value (``docs/reports.md#numbers``). Matched against the visible text of a page.
REPR_PATTERNS = {
    "None": r"\bNone\b",
    "True": r"\bTrue\b",
    "False": r"\bFalse\b",
    "nested list": r"\[\[",
    "dict repr": r"\{'",
    "nan": r"(?<![\w-])nan(?![\w-])",
    "NaN": r"(?<![\w-])NaN(?![\w-])",
}


class _Visible(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.parts: list[str] = []
        self._skip = 0

    def handle_starttag(self, tag, attrs):
        if tag in ("script", "style"):
            self._skip += 1
        for k, val in attrs:
            if k in ("alt", "title") and val:
                self.parts.append(val)

    def handle_endtag(self, tag):
        if tag in ("script", "style"):
            self._skip = max(self._skip - 1, 0)

    def handle_data(self, data):
        if not self._skip:
            self.parts.append(data)


def visible_text(html: str) -> str:
    """Return the text a reader of ``html`` sees, with ``alt`` and ``title`` texts.

    Scripts, styles and embedded image data are left out.
    """
    p = _Visible()
    p.feed(html)
    return " ".join(p.parts)


def find_reprs(text: str, patterns: Iterable[str] | None = None) -> list[str]:
    """Return ``"kind: …context…"`` for every Python repr found in ``text`` (visible text)."""
    out = []
    for kind, pat in REPR_PATTERNS.items():
        if patterns is not None and kind not in patterns:
            continue
        for m in re.finditer(pat, text):
            a, b = max(0, m.start() - 60), min(len(text), m.end() + 60)
            out.append(f"{kind}: …{' '.join(text[a:b].split())}…")
    return out
