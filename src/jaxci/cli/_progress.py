"""What a long command shows on stderr while it works: one line, redrawn in place on a terminal, that says the
phase, the stage inside it, the latest step, F, the worst element (max kappa/3) and the time since the command
started; and with ``--verbose`` a line per finished phase (its time and compilation) and per stage.

`Display` is a `jaxci.runtime.phases.PhaseClock` listener (``on_event``). The live line is drawn only where stderr is a
terminal (and not with ``--quiet``): piped or redirected, stderr gets nothing but the ``--verbose`` lines. The line
is a `rich.live.Live` display (rich is already loaded by the mesh reader, meshio: its live display adds 2-5 ms to
the command's start): its thread redraws the line twice a second, so that the elapsed time moves during a long
compiled call that reports nothing, and every event at once (a redraw costs about 0.2 ms; a loop reports a step
at most every `jaxci.runtime.phases.STEP_INTERVAL` seconds). `close` (always called, also on an error or an
interrupt) stops it and erases the line before anything else is printed. The line is cut to the terminal's width
(``COLUMNS`` where that is set).
"""

from __future__ import annotations

import sys
import time

#: Seconds between two redraws of the live line by the refresh thread.
REFRESH = 0.5


def _number(x) -> str:
    return "-" if x is None else f"{x:.6g}"


def step_text(rec: dict) -> str:
    """A ``"step"`` event's record as text: ``L-BFGS step 120: F 0.0123, worst kappa/3 1.234``."""
    text = f"{rec['stage']} {rec.get('unit', 'step')} {rec['step']}"
    if rec.get("F") is not None:
        text += f": F {_number(rec['F'])}"
        if rec.get("worst") is not None:
            text += f", worst kappa/3 {_number(rec['worst'])}"
    return text


class Display:
    """A `PhaseClock` listener writing to `stream` (default stderr).

    - `live`: draw the live line (the caller decides: stderr a terminal and no ``--quiet``; `wanted`).
    - `verbose`: print a line per finished phase and per stage (``--verbose``), on a terminal or not.
    - `started`: `time.perf_counter` value the elapsed time counts from (default: now).
    """

    def __init__(self, *, live: bool, verbose: bool = False, stream=None, started: float | None = None):
        self.stream = sys.stderr if stream is None else stream
        self.live, self.verbose = live, verbose
        self.started = time.perf_counter() if started is None else started
        self.context = ""  # what the whole command is at (`jaxci run`: the run), before the phase
        self._phase = ""
        self._detail = ""
        self._live = None
        if live:
            from rich.console import Console
            from rich.live import Live

            console = Console(file=self.stream, force_terminal=True, highlight=False, markup=False, emoji=False)
            self._live = Live(get_renderable=self._renderable, console=console, refresh_per_second=1 / REFRESH,
                              transient=True, redirect_stdout=False, redirect_stderr=False)
            self._live.start()

    # -- events --------------------------------------------------------------------------------------------
    def on_event(self, kind: str, name: str, rec: dict | None) -> None:
        if kind == "start":
            self._phase, self._detail = name, ""
        elif kind == "end":
            self._detail = ""
            if self.verbose and rec is not None:
                comp = (f" (compilation {rec['compile_seconds']:.2f} s, {rec['compiled']} compiled)"
                        if rec["compiled"] else "")
                self.print(f"jaxci: {name:<9} {rec['seconds']:8.2f} s{comp}")
        elif kind == "progress":
            self._phase, self._detail = name, rec["text"]
            if self.verbose:
                self.print(f"jaxci: {name:<9} ... {rec['text']}")
        elif kind == "step":
            self._phase, self._detail = name, step_text(rec)
        self._draw()

    def set_context(self, text: str) -> None:
        """What the command as a whole is doing (shown before the phase): `jaxci run`'s current run."""
        self.context, self._phase, self._detail = text, "", ""
        self._draw()

    def print(self, line: str) -> None:
        """Print a permanent line (above the live line, which is drawn again below it)."""
        if self._live is not None:
            self._live.console.print(line, soft_wrap=True)
        else:
            print(line, file=self.stream, flush=True)

    def close(self) -> None:
        """Stop the refresh thread and erase the live line (idempotent)."""
        live, self._live, self.live = self._live, None, False
        if live is not None:
            try:
                live.stop()
            except (OSError, ValueError):  # stderr gone: nothing to erase
                pass

    # -- the live line -------------------------------------------------------------------------------------
    def text(self) -> str:
        """The live line's text."""
        phase = (f"{self._phase}: {self._detail}" if self._detail else f"{self._phase} ...") if self._phase else ""
        body = " | ".join(part for part in (self.context, phase) if part)
        return f"jaxci: [{time.perf_counter() - self.started:6.1f} s] {body}".rstrip()

    def _renderable(self):
        from rich.text import Text

        return Text(self.text(), no_wrap=True, overflow="crop")

    def _draw(self) -> None:
        if self._live is None:
            return
        try:
            self._live.refresh()
        except (OSError, ValueError):  # stderr gone: nothing to show progress on
            self.close()


def wanted(quiet: bool) -> bool:
    """Whether to draw the live line: not `quiet`, and stderr is a terminal."""
    if quiet:
        return False
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):
        return False
