"""What the hostile-input tests share: the command run in-process in a folder (`run_in`: nothing but the asked-for
outputs may appear, change or disappear there), the one-line refusal contract (`assert_refused`), and a child
process for the cases that would hang or exhaust memory when the contract is broken (`run_in_child`)."""

from __future__ import annotations

import contextlib
import json
import os
import stat
import subprocess
import sys
from pathlib import Path

from jaxci.cli import main


def snapshot(folder) -> dict:
    """Every entry under `folder` (hidden ones too): relative path -> bytes, "<dir>", ("<link>", target) or, for
    a FIFO, a device or a socket (never opened), ("<special>", mode)."""
    out = {}
    for root, dirs, files in os.walk(folder):
        for name in dirs + files:
            p = Path(root) / name
            rel = p.relative_to(folder).as_posix()
            mode = p.lstat().st_mode
            if stat.S_ISLNK(mode):
                out[rel] = ("<link>", os.readlink(p))
            elif stat.S_ISDIR(mode):
                out[rel] = "<dir>"
            elif not stat.S_ISREG(mode):
                out[rel] = ("<special>", mode)
            else:
                out[rel] = p.read_bytes()
    return out


def changes(before: dict, after: dict) -> list[str]:
    """What differs between two snapshots, as readable lines."""
    lines = [f"appeared: {k}" for k in sorted(after.keys() - before.keys())]
    lines += [f"disappeared: {k}" for k in sorted(before.keys() - after.keys())]
    lines += [f"changed: {k}" for k in sorted(before.keys() & after.keys()) if before[k] != after[k]]
    return lines


@contextlib.contextmanager
def inside(folder):
    old = os.getcwd()
    os.chdir(folder)
    try:
        yield
    finally:
        os.chdir(old)


def cli(capsys, *argv) -> tuple[int, str, str]:
    capsys.readouterr()  # drop whatever was printed before (meshio's notes while building fixtures)
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


def cli_in(capsys, folder, *argv):
    with inside(folder):
        return cli(capsys, *argv)


def run_in(capsys, folder, *argv, outputs=()) -> tuple[int, str, str]:
    """`jaxci *argv` in `folder`; asserts the folder is untouched except `outputs` (names) on exit 0."""
    before = snapshot(folder)
    with inside(folder):
        rc, out, err = cli(capsys, *argv)
    after = snapshot(folder)
    allowed = set(outputs) if rc == 0 else set()
    diff = [c for c in changes(before, after) if c.split(": ", 1)[1] not in allowed]
    assert not diff, f"jaxci {' '.join(map(str, argv))}: rc {rc}, stderr {err!r}; working folder: {diff}"
    return rc, out, err


def assert_refused(rc, out, err, *mentions, what=""):
    """Exit 2, exactly one stderr line ``jaxci: error: ...``, no traceback; the line names each of `mentions`."""
    ctx = f"{what}: rc {rc}, stdout {out[-300:]!r}, stderr {err[-1500:]!r}"
    assert rc == 2, ctx
    assert "Traceback" not in err, ctx
    lines = err.strip().splitlines()
    assert len(lines) == 1, ctx
    assert lines[0].startswith("jaxci: error:"), ctx
    for m in mentions:
        assert m.lower() in lines[0].lower(), f"{ctx}: the message should name {m!r}"


def assert_ok(rc, out, err, what=""):
    ctx = f"{what}: rc {rc}, stderr {err[-1500:]!r}"
    assert rc == 0, ctx
    assert "Traceback" not in err and "internal error" not in err, ctx


#: The child process of `run_in_child`: `jaxci.cli.main` on each job, in its folder, under 8 GiB of address space.
_DRIVER = r"""
import contextlib, io, json, os, resource, sys, time
resource.setrlimit(resource.RLIMIT_AS, (8 << 30, 8 << 30))  # before JAX starts its threads
from jaxci.cli import main
for case, folder, argv in json.loads(sys.argv[1]):
    os.chdir(folder)
    out, err = io.StringIO(), io.StringIO()
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            rc = main(argv)
        except BaseException as e:
            rc = f"raised {type(e).__name__}: {e}"
    print(json.dumps({"case": case, "rc": rc, "out": out.getvalue()[-3000:], "err": err.getvalue()[-3000:],
                      "secs": time.perf_counter() - t0}), flush=True)
"""


def run_in_child(jobs: list, timeout: float = 240) -> tuple[dict, str]:
    """Run each job ``(case, folder, argv)`` by `jaxci.cli.main` in ONE child process (one JAX import) under
    8 GiB of address space, stopped after `timeout` seconds: ({case: {rc, out, err, secs}} of the jobs that
    finished, the child's stderr). A job that hangs leaves it and the jobs after it out of the result."""
    p = subprocess.Popen([sys.executable, "-c", _DRIVER, json.dumps([[c, str(f), a] for c, f, a in jobs])],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        out, err = p.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        p.kill()  # our own child, by its handle
        out, err = p.communicate()
    results = {}
    for line in out.splitlines():
        with contextlib.suppress(ValueError):
            r = json.loads(line)
            results[r["case"]] = r
    return results, err
