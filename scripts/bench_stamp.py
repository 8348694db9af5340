"""What every benchmark's JSON says of its own run: the commit, the date and the command.

Imported by name by the benchmarks beside it (their folder is on ``sys.path`` when they run); it imports none of
them, so `bench_gpu.py`, which runs the others' ``run`` functions, and those others never import each other."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def commit() -> str:
    """The checkout's commit (``git describe --always --dirty``), or "" without git."""
    try:
        return subprocess.run(["git", "-C", str(ROOT), "describe", "--always", "--dirty"], capture_output=True,
                              text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ""


def stamp() -> dict:
    """``{"commit", "date", "command"}`` of this run (the command: the script's name and its arguments)."""
    return {"commit": commit(), "date": time.strftime("%Y-%m-%d"),
            "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]])}
