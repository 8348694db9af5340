"""The command's standard output and error when they cannot be written: a reader that went away, a full device.

`checked()` (used by `jaxci.cli.main` around a command) puts a thin wrapper around ``sys.stdout`` and
``sys.stderr``:

- standard output: a write or flush that fails raises `OutputClosed` (the reader of a pipe went away,
  ``EPIPE``: ``jaxci quality m.vtk | head -c 1``) or `OutputFailed` (any other error: ``> /dev/full`` gives
  ``ENOSPC``), which `jaxci.cli` reports as such (exit 141 = 128 + SIGPIPE without a word, as a command killed by
  SIGPIPE ends; exit 2 and one line), never as an internal error. Every command prints its report only after its
  files are complete, so an output file written before is complete either way;
- standard error: a message that cannot be written is dropped (there is nowhere to say so), and the command
  goes on.

After a failure the stream's file descriptor is pointed at ``/dev/null`` (`_silence`), so that the flush at the
end of the process cannot fail again.
"""

from __future__ import annotations

import contextlib
import errno
import os
import sys


class OutputClosed(Exception):
    """Standard output is a pipe whose reader went away (``EPIPE``)."""


class OutputFailed(Exception):
    """Standard output cannot be written (the `OSError` is the cause)."""


def _silence(stream) -> None:
    """Point `stream`'s file descriptor at /dev/null, and drop what its buffer holds."""
    with contextlib.suppress(Exception):
        fd = stream.fileno()
        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, fd)
        os.close(null)


class _Checked:
    """A text stream whose write and flush errors are handled as the module docstring says."""

    def __init__(self, stream, is_stdout: bool):
        self._stream, self._stdout = stream, is_stdout

    def _failed(self, exc: OSError):
        _silence(self._stream)
        if not self._stdout:
            return None
        if exc.errno == errno.EPIPE:
            raise OutputClosed from None
        raise OutputFailed(exc.strerror or str(exc)) from exc

    def write(self, text):
        try:
            return self._stream.write(text)
        except OSError as exc:
            self._failed(exc)
            return len(text)

    def flush(self):
        try:
            self._stream.flush()
        except OSError as exc:
            self._failed(exc)

    def __getattr__(self, name):
        return getattr(self._stream, name)


@contextlib.contextmanager
def checked():
    """Within the block, ``sys.stdout`` and ``sys.stderr`` are wrapped (module docstring)."""
    out, err = sys.stdout, sys.stderr
    sys.stdout, sys.stderr = _Checked(out, True), _Checked(err, False)
    try:
        yield
    finally:
        sys.stdout, sys.stderr = out, err


def say(line: str) -> None:
    """Print one line on standard error; dropped if it cannot be written."""
    try:
        print(line, file=sys.stderr, flush=True)
    except (OSError, ValueError):
        _silence(sys.stderr)
