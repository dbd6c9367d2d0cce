"""Small helpers shared by the benchmark scripts."""

from __future__ import annotations

import os
import sys


def log(msg: str) -> None:
    """Progress to stderr (tables go to stdout)."""
    print(msg, file=sys.stderr, flush=True)


def load1() -> float:
    """1-minute load average, printed beside timings on a shared machine."""
    return os.getloadavg()[0]
