"""SIGINT and SIGTERM for the jaxci command: acted on within about a second, finished work kept, no litter.

Python runs a signal handler in the main thread only, between two bytecodes: while the main thread waits in a
long jitted XLA call (which releases the GIL) a plain handler waits for the call to return (50 s for a Ctrl-C
during the local CI of a 30^3 box). `guard()` (used by `jaxci.cli.main` around a command; this module installs
nothing when imported, and nothing when `main` runs outside the main thread) installs:

- a handler for SIGINT and SIGTERM that records the first signal and raises `KeyboardInterrupt` in the main
  thread: the normal path, where the command's own clean-up runs (``jaxci run`` writes its finished runs). A
  `jaxci.experiments.results.uninterrupted` block (the renames that swap a results folder) gets the interrupt at its
  end. jaxlib polls for signals while it waits for a computation, so the handler usually runs at once; but it may
  run inside JAX's garbage-collector callback, where Python ignores exceptions: then (`_swallowed_in`, or
  `sys.unraisablehook` for the cases it misses) a one-shot `sys.setprofile` hook raises the interrupt at the
  first call or return outside such a callback;
- `signal.set_wakeup_fd` on a pipe, read by a daemon watchdog thread. If the handler has not run `GRACE`
  seconds after a signal (the main thread is inside a long native call), or at a second signal, the watchdog
  does the clean-up itself: it calls the functions registered with `on_interrupt`, last first (``jaxci run``
  writes its finished runs; `removing_temporaries` removes an atomic write's temporary files), prints the one
  line ``jaxci: interrupted (SIGTERM): ...`` on stderr and ends the process with `os._exit`. Once it has begun,
  the main thread's handler blocks, so the main thread never continues past the native call.

Once an output is complete the command says so (`completed`), and the line of a later interrupt names it. With
``guard(keep_handlers=True)`` (`jaxci.cli.entry`) the handlers stay until the process ends, so that a signal after
the command (while the exit handlers run) is reported too, not a silent death by the default action.

Exit code 128 + the signal number: 130 for SIGINT, 143 for SIGTERM. A signal that the parent process set to
be ignored (``nohup``, a background job) stays ignored.
"""

from __future__ import annotations

import contextlib
import gc
import os
import select
import shutil
import signal
import sys
import threading
import time
from pathlib import Path

#: Seconds the watchdog gives the main thread to act on a signal (its handler to run) ...
GRACE = 1.0
#: ... and to finish the command once it has (a KeyboardInterrupt can be lost in a native call that polls
#: for signals and ignores the error, or the clean-up can run into another long native call).
FINISH = 3.0
SIGNALS = (signal.SIGINT, signal.SIGTERM)


def _swallowed_in(frame) -> bool:
    """Whether an exception raised in `frame` would be ignored by Python: inside a garbage-collector callback
    (JAX registers one), a ``__del__`` or the guard's own ``sys.unraisablehook`` (an exception raised there is
    only printed, "Exception ignored in sys.unraisablehook", and the interrupt would be lost)."""
    codes = {getattr(getattr(cb, "__func__", cb), "__code__", None) for cb in gc.callbacks}
    codes.add(Guard._unraisable.__code__)
    while frame is not None:
        if frame.f_code in codes or frame.f_code.co_name == "__del__":
            return True
        frame = frame.f_back
    return False


def signal_name(signum: int | None) -> str:
    return signal.Signals(signum or signal.SIGINT).name


class _Interrupt(KeyboardInterrupt):
    """The `KeyboardInterrupt` raised by the guard's signal handler."""


class Guard:
    """The signal state of one command: the first signal (`signum`), the registered clean-up functions."""

    def __init__(self):
        self.lock = threading.Lock()
        self.signum: int | None = None
        self.finishers: list = []
        self._raised = False  # the main thread was given its KeyboardInterrupt (first signal)
        self._handled = False  # the main thread's handler ran
        self._emergency = False  # the watchdog is ending the process
        self._closed = False  # the command is over
        self._count = 0  # signals seen by the watchdog
        self._old_unraisable = sys.unraisablehook
        self.done: list[str] = []  # outputs complete so far (`completed`), for the interrupt's line

    @property
    def detail(self) -> str:
        """What the command has completed (`completed`), for the line of an interrupt that comes after."""
        return "; ".join(self.done)

    @property
    def exit_code(self) -> int:
        return 128 + int(self.signum or signal.SIGINT)

    # ------------------------------------------------------------------------------------ main thread
    def _handler(self, signum, frame) -> None:
        with self.lock:
            if self.signum is None:
                self.signum = signum
            emergency = self._emergency
            first = not (self._raised or self._closed or emergency)
            self._raised = self._raised or first
            self._handled = True
        if emergency:  # the watchdog is cleaning up and ending the process: go no further
            while True:
                time.sleep(60)
        if first:
            self._raise(frame)

    def _raise(self, frame) -> None:
        """Raise the interrupt in `frame`, at the end of a `jaxci.experiments.results.uninterrupted` block, or, where
        Python would ignore it, at the first profile event outside such a place."""
        from ..experiments.results import defer_interrupt

        if _swallowed_in(frame):
            sys.setprofile(self._profile)
        elif not defer_interrupt():
            raise _Interrupt

    def _profile(self, frame, event, arg) -> None:
        if _swallowed_in(frame):
            return
        sys.setprofile(None)
        with self.lock:
            closed = self._closed
        if not closed:
            self._raise(frame)

    def _unraisable(self, info) -> None:
        """`sys.unraisablehook`: the interrupt was raised where Python ignores exceptions (a place that
        `_swallowed_in` does not recognise, such as a weakref callback): raise it again at the next event."""
        if not isinstance(info.exc_value, _Interrupt):
            self._old_unraisable(info)
            return
        sys.setprofile(self._profile)

    # ------------------------------------------------------------------------------------ watchdog thread
    def _watch(self, fd: int) -> None:
        first = None  # time of the first signal
        try:
            while True:
                timeout = None
                if first is not None:
                    timeout = max(0.0, first + (FINISH if self._handled else GRACE) - time.monotonic())
                ready, _, _ = select.select([fd], [], [], timeout)
                if not ready:  # the main thread did not act on the signal in time, or did not finish
                    self._emergency_exit(force=not self._handled or time.monotonic() >= first + FINISH)
                    continue
                for b in os.read(fd, 64):
                    if b == 0:  # stop: the command is over
                        return
                    if b not in SIGNALS:
                        continue
                    with self.lock:
                        self._count += 1
                        if self.signum is None:
                            self.signum = b
                    if self._count >= 2:
                        self._emergency_exit(force=True)
                    elif first is None:
                        first = time.monotonic()
        finally:
            os.close(fd)

    def _emergency_exit(self, force: bool) -> None:
        """Unless the command is over or `force` is False: call the finishers, print the line, `os._exit`."""
        with self.lock:
            if self._closed or self._emergency or not force:
                return
            self._emergency = True
        details = []
        for fn in reversed(self.finishers):
            try:
                detail = fn()
            except BaseException as e:  # noqa: BLE001 - the process is ending; say what failed
                detail = f"clean-up failed ({type(e).__name__}: {e})"
            if detail:
                details.append(detail)
        details = details or self.done
        line = f"jaxci: interrupted ({signal_name(self.signum)})" + (": " + "; ".join(details) if details else "")
        if os.isatty(2):
            line = "\r\x1b[2K\x1b[?25h" + line  # clear a progress bar's line, show the cursor again
        with contextlib.suppress(OSError):
            os.write(2, (line + "\n").encode())
        os._exit(self.exit_code)

    def claim_exit(self) -> None:
        """Called by the main thread before it reports an interrupt: if the watchdog is already ending the
        process, wait for it (one message, one exit code); else the watchdog stands down."""
        with self.lock:
            emergency = self._emergency
            self._closed = True
        while emergency:
            time.sleep(60)


_ACTIVE: list[Guard] = []


@contextlib.contextmanager
def guard(keep_handlers: bool = False):
    """Install the handlers and the watchdog for one command; yields the `Guard`. Outside the main thread it
    installs nothing (a `Guard` that sees no signal). `keep_handlers`: leave the signal handlers installed at the
    end (the watchdog stopped): a signal then is only recorded in `Guard.signum`, for the caller to report, up to
    the process's end (`jaxci.cli.entry`, whose exit handlers run after the command); with the default handlers
    back it would end the process at once, without a word."""
    g = Guard()
    if threading.current_thread() is not threading.main_thread():
        yield g
        return
    r, w = os.pipe()
    os.set_blocking(w, False)
    old = {}
    for s in SIGNALS:
        current = signal.getsignal(s)
        if current is not signal.SIG_IGN:
            old[s] = signal.signal(s, g._handler)
    old_fd = signal.set_wakeup_fd(w, warn_on_full_buffer=False)
    g._old_unraisable, sys.unraisablehook = sys.unraisablehook, g._unraisable
    thread = threading.Thread(target=g._watch, args=(r,), daemon=True, name="jaxci-interrupt-watchdog")
    thread.start()
    _ACTIVE.append(g)
    try:
        yield g
    finally:
        with g.lock:
            g._closed = True
            emergency = g._emergency
        while emergency:  # the watchdog is ending the process
            time.sleep(60)
        _ACTIVE.remove(g)
        if sys.getprofile() == g._profile:
            sys.setprofile(None)
        sys.unraisablehook = g._old_unraisable
        signal.set_wakeup_fd(old_fd)
        for s, h in old.items():
            if not keep_handlers:
                signal.signal(s, h if h is not None else signal.SIG_DFL)
        with contextlib.suppress(OSError):
            os.write(w, b"\0")
        thread.join(timeout=5)
        os.close(w)


def completed(detail: str) -> None:
    """Note that an output of the command is complete (``detail``: what and where, e.g. "wrote out.vtk
    (complete)"): the line of an interrupt that comes later says so. No-op outside `guard`."""
    if _ACTIVE:
        _ACTIVE[-1].done.append(detail)


def signalled() -> bool:
    """Whether the command's guard has seen SIGINT or SIGTERM (for an error that the interrupt caused inside a
    library, which wrapped the `KeyboardInterrupt` in its own exception: a JAX callback does)."""
    return bool(_ACTIVE) and _ACTIVE[-1].signum is not None


@contextlib.contextmanager
def on_interrupt(fn):
    """Within the block, the watchdog calls ``fn()`` (from its own thread, the main thread being stuck) before
    it ends the process; ``fn`` returns a short text for the message line, or None. No-op outside `guard`."""
    g = _ACTIVE[-1] if _ACTIVE else None
    if g is None:
        yield
        return
    g.finishers.append(fn)
    try:
        yield
    finally:
        g.finishers.remove(fn)


@contextlib.contextmanager
def removing_temporaries(target: str | os.PathLike):
    """Within the block, an emergency exit removes the temporary folders of an atomic write of `target` that this
    process made beside it (``.jaxci-tmp-<pid>-<name>.*``, `jaxci.io._place.make_temporary`, as
    `jaxci.io.write_mesh` and `jaxci.experiments.results.stage` make). A SIGKILL, which no handler sees, leaves
    them: the next write in that folder removes them (`jaxci.io._place.remove_stale`)."""
    from ..io._place import temporary_prefix

    target = Path(target)
    folder = target.parent
    prefix = temporary_prefix(target.name)

    def clean() -> None:
        try:
            ours = [e for e in os.listdir(folder) if e.startswith(prefix)]
        except OSError:
            return
        for name in ours:
            p = folder / name
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p, ignore_errors=True)
            else:
                with contextlib.suppress(OSError):
                    p.unlink()

    with on_interrupt(clean):
        yield
