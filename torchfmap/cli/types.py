"""argparse types of the command line: each refuses a bad value with a message naming it."""

from __future__ import annotations

import argparse
import math

import numpy as np


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1 or str(value) != text.strip().lstrip("+"):
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {text!r}")
    return value


def _finite_float(text: str, strict: bool) -> float:
    """``text`` as a finite float ``> 0`` (``strict``) or ``>= 0``, else an argparse error."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and (value > 0 if strict else value >= 0)):
        raise argparse.ArgumentTypeError(f"must be a finite number {'>' if strict else '>='} 0, got {text!r}")
    return value


def nonnegative_float(text: str) -> float:
    """argparse type: a finite number >= 0."""
    return _finite_float(text, strict=False)


def positive_float(text: str) -> float:
    """argparse type: a finite number > 0."""
    return _finite_float(text, strict=True)


def count(text: str) -> int:
    """argparse type: an integer >= 0."""
    if text.strip() == "0":
        return 0
    try:
        return positive_int(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"must be an integer >= 0, got {text!r}") from None


def time_list(text: str) -> list[float]:
    """argparse type: comma-separated finite times > 0 (an empty list is refused)."""
    if not text.strip():
        raise argparse.ArgumentTypeError(
            "times must not be empty. Fix: omit --times for the default, or give e.g. 0.01,0.03"
        )
    try:
        times = [float(t) for t in text.split(",")]
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"times must be comma-separated numbers, got {text!r}") from err
    if not all(np.isfinite(t) and t > 0 for t in times):
        raise argparse.ArgumentTypeError(f"times must be finite and > 0, got {text!r}")
    return times


def point_count(text: str) -> int | str | None:
    """argparse type of ``--max-points``: ``'auto'``, ``'all'`` (None: every point) or an integer >= 1."""
    if text.strip() in ("auto", "all"):
        return None if text.strip() == "all" else "auto"
    try:
        return positive_int(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"must be auto, all or an integer >= 1, got {text!r}") from None
