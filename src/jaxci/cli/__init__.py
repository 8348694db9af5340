"""The `jaxci` command line: one module per subcommand, each with `add_args(parser)` and `run(args)`.

`main(argv)` returns the exit code: 0 on success, 2 for any error the user can fix (bad file, bad mesh, bad
config, an output that exists or is an input: one line on stderr, no traceback, nothing written; also a standard
output that cannot be written, such as ``> /dev/full``), 1 for a bug of ours ("internal error"), 130 on SIGINT
(Ctrl-C) and 143 on SIGTERM, acted on within about a second even during a long computation (`_interrupt`:
finished work kept, temporary files removed, one line on stderr; a signal that comes as the command ends still
gives its exit code), and 141 (128 + SIGPIPE), without a word, when standard output is a pipe whose reader went
away (``| head -c 1``: `_streams`). Library code never prints, exits or handles signals; only this does.

Commands that write (``smooth``, ``classify``, ``generate``, ``run``) refuse an existing output unless given
``--force`` and never write over one of their inputs (`_files`); every output is written atomically.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import warnings

from ..runtime import compile_cache
from ..runtime._lazy import when_imported
from ..runtime.process import TUNABLE, apply_cpu_device_flags
from . import _interrupt, _streams

#: subcommand -> (module, one-line help)
COMMANDS = {
    "quality": ("_quality", "report the quality of a hexahedral mesh"),
    "generate": ("_generate", "write a structured (optionally perturbed) box mesh"),
    "smooth": ("_smooth", "smooth a mesh (move nodes, keep connectivity) and write it"),
    "classify": ("_classify", "write the boundary node classes of a mesh as point data"),
    "run": ("_run", "run an experiment config (YAML): every mesh x method x seed, with report and figures"),
}


#: Exit codes of an interrupt: 128 + SIGINT, 128 + SIGTERM.
INTERRUPTED = (130, 143)
#: Exit code when standard output is a pipe whose reader went away: 128 + SIGPIPE, as a command killed by it.
CLOSED_OUTPUT = 141


def setup_jax() -> None:
    """float64 for reports, and the compilation cache (`jaxci.runtime.compile_cache`) so a second CLI call skips
    compiling.

    Set when JAX is imported, not before: a small mesh's run (numpy path, `jaxci.optim.host`) never imports it
    (0.4-0.5 s of a 1-2 s run); one that does gets float64 through JAX's environment variable and the cache
    (the library's set-up, at the same place, ``JAXCI_CACHE_DIR=`` to turn it off) as soon as it imports JAX."""
    if "jax" in sys.modules:
        import jax

        jax.config.update("jax_enable_x64", True)
    else:
        os.environ["JAX_ENABLE_X64"] = "True"
    when_imported("jax", compile_cache.enable)


class _Version(argparse.Action):
    """``--version``: the line is made when asked for (it imports JAX, which a run on the numpy path never does)."""

    def __call__(self, parser, namespace, values, option_string=None):
        import jax

        from .. import __version__

        pages = "on" if TUNABLE in os.environ.get("GLIBC_TUNABLES", "") else "off"
        print(f"jaxci {__version__} (jax {jax.__version__}; huge pages for glibc allocations {pages} "
              f"(jaxci.runtime.process))")
        parser.exit(0)


class _Parser(argparse.ArgumentParser):
    """argparse with its usage errors as ONE line on stderr (``jaxci: error: ...``, exit 2), like every other
    error of the command; the usage is one ``--help`` away.

    A subcommand whose parser has ``intermixed = True`` (``smooth``, whose one positional takes one or more paths)
    reads options and positionals in any order (`argparse.ArgumentParser.parse_known_intermixed_args`): ``jaxci
    smooth IN --method M OUT`` gives IN and OUT as two separate positionals did."""

    intermixed = False
    _inside = False

    def parse_known_args(self, args=None, namespace=None):
        if not self.intermixed or self._inside:
            return super().parse_known_args(args, namespace)
        self._inside = True  # parse_known_intermixed_args calls this method twice
        try:
            return self.parse_known_intermixed_args(args, namespace)
        finally:
            self._inside = False

    def error(self, message: str):
        self.exit(2, f"jaxci: error: {self.prog}: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="jaxci", description="Hexahedral mesh quality and smoothing in JAX.")
    parser.add_argument("--version", action=_Version, nargs=0, help="show the version (and JAX's) and exit")
    parser.add_argument("--debug", action="store_true", help="show tracebacks of errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, (mod, help_) in COMMANDS.items():
        p = sub.add_parser(name, help=help_, description=help_)
        module = importlib.import_module(f".{mod}", __name__)
        module.add_args(p)
        p.set_defaults(_run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the CLI with `argv` (default ``sys.argv[1:]``) and return the exit code."""
    with _interrupt.guard() as guard:
        code = _guarded(argv, guard)
    return _ended(guard, code)


def _guarded(argv, guard) -> int:
    """`_main` under the interrupt `guard`: its exit code, or 130 / 143 with the interrupt's line."""
    with _streams.checked():
        try:
            code = _main(argv)
            guard.claim_exit()  # from here on a signal is only recorded (`_ended` reports it)
            return code
        except KeyboardInterrupt as e:  # SIGINT or SIGTERM (`_interrupt`); a command may add what it kept
            guard.claim_exit()
            detail = e.args[0] if e.args and isinstance(e.args[0], str) else guard.detail
            _streams.say(f"jaxci: interrupted ({_interrupt.signal_name(guard.signum)})"
                         + (f": {detail}" if detail else ""))
            return guard.exit_code


def _ended(guard, code: int) -> int:
    """The exit code, and the interrupt's line, of a signal that came as the command ended: not lost."""
    if guard.signum is None or code in INTERRUPTED:
        return code
    done = f" ({guard.detail})" if guard.detail else ""
    _streams.say(f"jaxci: interrupted ({_interrupt.signal_name(guard.signum)}) as the command ended; its output "
                 f"was complete{done}" + ("" if code == 0 else f" (exit status {code} without the signal)"))
    return guard.exit_code


def _main(argv) -> int:
    try:
        parser = build_parser()
        try:
            args = parser.parse_args(argv)
        except SystemExit as e:  # argparse: --help (0) or a usage error (2)
            sys.stdout.flush()
            return int(e.code or 0)
        apply_cpu_device_flags()  # more forced CPU devices than cores: no per-fusion partitions (docs/sharding.md)
        setup_jax()
        return _dispatch(args)
    except _streams.OutputClosed:  # `| head`: the reader has all it wanted
        return CLOSED_OUTPUT
    except _streams.OutputFailed as e:
        _streams.say(f"jaxci: error: cannot write to standard output ({e}); any output file was written whole")
        return 2


def _dispatch(args) -> int:
    from ..errors import JaxciError

    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            code = args._run(args)
        for w in caught:
            if issubclass(w.category, UserWarning):
                _streams.say(f"jaxci: warning: {w.message}")
        sys.stdout.flush()  # a closed or full standard output is found here, not at the process's end
        return int(code or 0)
    except (_streams.OutputClosed, _streams.OutputFailed):
        raise
    except JaxciError as e:
        if args.debug:
            raise
        _streams.say(f"jaxci: error: {e}")
        return 2
    except Exception as e:  # a bug of ours: one line, the traceback only with --debug
        if _interrupt.signalled():  # the interrupt, wrapped by a library (an error raised in a JAX callback)
            raise KeyboardInterrupt from e
        if args.debug:
            raise
        _streams.say(f"jaxci: internal error: {type(e).__name__}: {e} (run with --debug for the traceback)")
        return 1


def entry() -> None:  # pragma: no cover - console script
    """The command: `main`, then out of the process without the interpreter's shutdown. Every output is complete
    by then (written atomically, temporaries removed), so only the exit handlers and the streams are left:
    tearing down JAX and every module cost 0.2-0.3 s after a 1.5 s run (a quarter of a small mesh's wall time),
    and after an interrupt it would wait for an XLA computation to finish. The signal handlers stay until the
    end (`_interrupt.guard`'s ``keep_handlers``): a SIGINT or SIGTERM while the exit handlers run still gives
    its line and exit code."""
    import atexit
    import logging

    with _interrupt.guard(keep_handlers=True) as guard:
        code = _guarded(None, guard)
    try:
        if code not in INTERRUPTED:
            atexit._run_exitfuncs()  # what sys.exit would run: JAX's and logging's handlers
            logging.shutdown()
    finally:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):  # reported already (`_streams`), or nowhere to report it
                pass
        os._exit(_ended(guard, code))
