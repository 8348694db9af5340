"""The project speaks of itself only: no numbered stages of past development work ("session 12", "issue 17") in
any tracked text file (code, comments, docstrings, docs, configs, tests, JSON) or file name. A measurement cites
its date and commit, or the benchmark that made it. (The paper's "stage 1 / stage 2" of Cohort Intelligence, and
"stage N of the flow" of the package layout, are not development stages.)"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

#: What development-process words look like (case-insensitive).
PATTERNS = [
    re.compile(p, re.IGNORECASE) for p in (
        r"\bsessions? ?\d",                # session 12, Session 8's, sessions 7-9
        r"\bsession\d",                   # session17 (a JSON value)
        r"_session\d",                     # bench_realmesh_session17.json
        r"\bsession's\b",                  # at the session's final code
        r"\b(?:this|that|next|previous|earlier|last) session\b",
        r"\bissues? ?#?\d+",               # issue 17, issues 14, 17, issue #5
        r"\bstage \d+ of (?:our|the|this) (?:work|project|development)",
    )
]


def hits(text: str) -> list[tuple[int, str]]:
    """``(line number, line)`` of each line of `text` with a development-process word."""
    return [(i, line.strip()) for i, line in enumerate(text.splitlines(), 1)
            if any(p.search(line) for p in PATTERNS)]


def _tracked() -> list[Path]:
    try:
        out = subprocess.run(["git", "ls-files", "-z"], cwd=REPO, capture_output=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout")
    return [REPO / name for name in out.decode().split("\0") if name]


def test_the_patterns_catch_what_they_should_and_only_that():
    bad = ["measured in session 12", "Session 8's cohorts", "bench_realmesh_session17.json", '"code": "session17"',
           "at the session's final code", "(issue 17, item 3)", "Issue 15: on pave3", "issues 14, 17",
           "stage 3 of our work"]
    good = ["the paper's stage 1 (roulette)", "CI global stage 2", "Stage 6 of the flow: experiment configs",
            "written once per session", "session control commands of ANSYS", "what this issues is a warning",
            "2026-11-26, commit 36df970"]
    assert all(hits(t) for t in bad), [t for t in bad if not hits(t)]
    assert not any(hits(t) for t in good), [t for t in good if hits(t)]


def test_no_development_process_words_in_tracked_files():
    me = Path(__file__).resolve()
    found = []
    for path in _tracked():
        rel = path.relative_to(REPO)
        if hits(str(rel)):
            found.append(f"{rel}: the file name")
        if path.resolve() == me or not path.is_file():
            continue
        data = path.read_bytes()
        if b"\0" in data[:8192]:  # binary (images, compiled objects)
            continue
        found += [f"{rel}:{i}: {line[:100]}" for i, line in hits(data.decode("utf-8", errors="replace"))]
    assert not found, "development-process words (cite a date and commit, or the benchmark):\n" + "\n".join(found)
