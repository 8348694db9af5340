"""`jaxci smooth IN... --out-dir DIR [--jobs N] [options]`: many meshes in one command, over the machine's cores.

Each IN is a mesh file or a folder (every file in it whose extension jaxci reads and writes, `_extensions`, sorted;
not its subfolders, not hidden files). Each input is written to DIR under its own file name, so in its own format.
Before any work the command refuses, as a whole (exit 2, one line naming the files, nothing written): two inputs
that would write the same output (or companion) name, and an output that would be one of the inputs. Then DIR is
made if missing and every output is checked (`_files.check_output`: an existing one only with ``--force``); a file
that fails its check fails alone, with the single form's line and status.

The files are smoothed by ``--jobs N`` worker processes (default: the cores this process may use, at most the
number of files), started with ``spawn`` (never ``fork`` after JAX is imported), each taking the next file when
it is done, the largest first; with one job they run in this process. A worker runs the single form's per-file
work (`_smooth_file.smooth_file`, with the same `_smooth_file.Settings`), so every per-file guarantee holds: the
output's format is the input's, it is written atomically, only what its check saw is replaced, the input is never
modified. Each worker's C kernels run on ``cores // jobs`` threads (``JAXCI_THREADS``; XLA's pool: ``NPROC``)
unless the environment sets them (`worker_environment`): a mesh over 512 hexahedra per thread (`jaxci.native`) can
then differ from the single form's in the last bits, as the single form run with that ``JAXCI_THREADS`` does.

A file that fails (unreadable, inverted and not untangled, an output that exists without ``--force``, ...) does
not stop the others: its error line goes to stderr and its status to the table. Exit status: 0 if every file
succeeded, else the largest per-file status (2 a user error, 3 elements left inverted, 1 an internal error). A
worker process that dies (killed, a crash in native code) fails the file it was smoothing (status 1, a line
saying how the worker ended: the signal that killed it, or its exit status); the other files not done run on a new
pool (`RESTARTS` times at most).

The output is one table (a row per file: hexahedra, worst element max kappa/3 and mean kappa/3 before -> after,
seconds, status) and a total line; ``--json`` prints one object instead: ``files`` (per file, the single form's
JSON object with ``exit_code``, ``error``, ``seconds`` and ``warnings``; a failed file has ``input``, ``output``,
``exit_code``, ``error``, ``seconds``) and ``totals``. ``--verbose`` adds a line per finished file on stderr.

Ctrl-C (SIGINT) or SIGTERM: the files not started are dropped, the workers are stopped (each removes its
temporary files: `_interrupt`), the outputs already complete stay, no partial or temporary file is left in DIR,
and the command exits 130 (143).
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import time
from pathlib import Path

#: Seconds between two looks at the workers (the live line is redrawn as often).
POLL = 0.5
#: Seconds the workers get to stop after SIGTERM before they are killed (their own guard ends them within about
#: `_interrupt.GRACE`); within the `_interrupt.FINISH` the command's own guard gives it.
STOP_WAIT = 1.5
#: New pools after a worker died, for the files it had not begun.
RESTARTS = 3


def _extensions() -> frozenset[str]:
    """The extensions a folder's files are taken by: what jaxci reads and writes (ANSYS listings are read only)."""
    from ..io import FORMATS

    return frozenset(ext for ext, fmt in FORMATS.items() if fmt != "ansys-listing")


def expand(paths) -> list[Path]:
    """The input files: each path as given, a folder replaced by its mesh files (sorted by name). A folder with
    none is a `ConfigError` (a mistake, not an empty batch)."""
    from ..errors import ConfigError

    exts = _extensions()
    files = []
    for p in map(Path, paths):
        if not p.is_dir():
            files.append(p)
            continue
        found = sorted(e for e in p.iterdir() if not e.name.startswith(".") and e.suffix.lower() in exts
                       and e.is_file())
        if not found:
            raise ConfigError(f"{p}: a folder without mesh files (extensions {', '.join(sorted(exts))}); nothing "
                              f"was written")
        files.extend(found)
    return files


def refuse_clashes(inputs: list[Path], outputs: list[Path]) -> None:
    """A `MeshWriteError` naming the files if two inputs would write the same output (or companion) name, or an
    output would be one of the inputs (`_files.refuse_inputs`)."""
    from ..errors import MeshWriteError
    from ._files import refuse_inputs, targets_of

    seen: dict[str, Path] = {}
    for src, out in zip(inputs, outputs, strict=True):
        for target in targets_of(out):
            other = seen.setdefault(os.path.normcase(os.path.abspath(target)), src)
            if other is not src:
                raise MeshWriteError(f"{other} and {src} would both write {target}; give inputs distinct file "
                                     f"names (nothing was written)")
    for out in outputs:
        refuse_inputs(out, inputs)


def _out_dir(path: str) -> Path:
    """DIR, made if missing (with its parents)."""
    from ..errors import MeshWriteError
    from ..io._paths import os_reason

    folder = Path(path)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise MeshWriteError(f"{folder}: exists and is not a folder (nothing was written)") from None
    except OSError as exc:
        raise MeshWriteError(f"{folder}: cannot make the output folder ({os_reason(exc)}); nothing was "
                             f"written") from None
    return folder


def _failed(src, dst, code: int, error: str) -> dict:
    return {"input": str(src), "output": str(dst), "exit_code": code, "error": error, "seconds": 0.0,
            "warnings": []}


def smooth_one(src: str, out, settings, debug: bool = False) -> dict:
    """One file, in a worker or in this process: `_smooth_file.smooth_file` and its JSON object
    (`_smooth_file.summary`) with ``exit_code`` and ``error`` (`_smooth_file.exit_status`), or the error line and
    the status the single form would give (2 a `JaxciError`, 1 anything else: an internal error, its traceback in
    ``traceback`` with ``--debug``); ``seconds`` (wall) and ``warnings``. An interrupt is raised, not recorded."""
    import warnings

    from ..errors import JaxciError
    from ..runtime.phases import PhaseClock
    from ._interrupt import signalled
    from ._smooth_file import exit_status, smooth_file, summary

    started = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            clock = PhaseClock()
            _, res = smooth_file(src, out, settings, clock)
            code, line = exit_status(res)
            rec = {**summary(res, clock.as_dict(), src, out.path), "exit_code": code, "error": line}
        except JaxciError as e:
            rec = _failed(src, out.path, 2, str(e))
        except Exception as e:
            if signalled():  # the interrupt, wrapped by a library
                raise KeyboardInterrupt from e
            rec = _failed(src, out.path, 1, f"internal error: {type(e).__name__}: {e}")
            if debug:
                import traceback

                rec["traceback"] = traceback.format_exc()
    rec["seconds"] = time.perf_counter() - started
    rec["warnings"] = [str(w.message) for w in caught if issubclass(w.category, UserWarning)]
    return rec


# ------------------------------------------------------------------------------------------- worker processes
def _leave(signum, frame) -> None:  # pragma: no cover - runs in a worker
    os._exit(128 + signum)


#: Where a worker says which file it begins (`_start_worker`).
_BEGUN = None


def _start_worker(begun) -> None:  # pragma: no cover - runs in a worker
    """A worker's set-up: SIGINT ignored (a Ctrl-C reaches the whole process group; the command stops its workers
    itself, with one SIGTERM each); between two files SIGTERM ends it at once and quietly (nothing of its own is
    open), during a file `_work`'s guard handles it; JAX set up as the command sets it up; the smoothing path
    imported before the first file is timed."""
    from ..runtime.process import apply_cpu_device_flags
    from . import setup_jax

    global _BEGUN
    _BEGUN = begun
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _leave)
    apply_cpu_device_flags()
    setup_jax()
    from .. import interface, io  # noqa: F401


def _work(index: int, src: str, out, settings, debug: bool) -> dict:  # pragma: no cover - runs in a worker
    """File `index` in a worker (said first: `_run_pool` fails it if the worker dies), under the command's signal
    guard (`_interrupt.guard`): an interrupt removes the write's temporary files and ends the worker (the command
    is stopping it)."""
    from . import _interrupt

    _BEGUN.put((index, os.getpid()))
    with _interrupt.guard() as guard:
        try:
            rec = smooth_one(src, out, settings, debug)
            # what it wrote (nothing where it wrote nothing), said before its record goes back: where the pool
            # breaks before the record arrives (another worker died), the file is tried again on a new pool, which
            # may then replace this output, and only it
            if out.written is not None:
                _BEGUN.put((index, list(out.written)))
            return rec
        except KeyboardInterrupt:
            signal.signal(signal.SIGTERM, signal.SIG_IGN)  # the pool sends one more when another worker ends
            guard.claim_exit()
    os._exit(guard.exit_code)


def worker_environment(jobs: int) -> dict[str, str]:
    """What the environment of `jobs` workers adds, where the user set none of it: no OpenBLAS threads; and where
    ``cores // jobs`` is fewer than the C kernels' threads of this process (`jaxci.native.THREADS`), that many
    for each worker's C kernel calls (``JAXCI_THREADS``) and XLA's pool (``NPROC``). (``JAXCI_THREADS`` is part of
    the keys of the stored programs: the workers store their own, beside the single form's, in the same cache.)"""
    from .. import native
    from ..runtime.process import schedulable_cpus

    env = {} if "OPENBLAS_NUM_THREADS" in os.environ else {"OPENBLAS_NUM_THREADS": "1"}
    threads = max(1, schedulable_cpus() // jobs)
    if "JAXCI_THREADS" in os.environ or threads >= native.THREADS:
        return env
    env["JAXCI_THREADS"] = str(threads)
    if "NPROC" not in os.environ:
        env["NPROC"] = str(threads)
    return env


@contextlib.contextmanager
def _environment(values: dict[str, str]):
    """Within the block, ``os.environ`` has what the workers start with (`values`), and SIGINT is ignored, so
    that a worker starting up inherits it ignored until `_start_worker` (a Ctrl-C then would print a traceback
    per worker). Both are put back at the end of the block."""
    old = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    handler = None
    with contextlib.suppress(ValueError):  # not the main thread
        handler = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        if handler is not None:
            signal.signal(signal.SIGINT, handler)
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _stop(pool, folder: Path) -> None:
    """Stop the workers (SIGTERM; SIGKILL after `STOP_WAIT`), drop the files not started, remove what a killed
    worker left in `folder` (`jaxci.io._place.remove_stale`)."""
    from ..io._place import remove_stale

    procs = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for p in procs:
        if p.is_alive():
            p.terminate()
    deadline = time.monotonic() + STOP_WAIT
    for p in procs:
        p.join(max(0.0, deadline - time.monotonic()))
    for p in procs:
        if p.is_alive():
            p.kill()
            p.join(1.0)
    remove_stale(folder)


def _run_pool(items, settings, jobs: int, folder: Path, debug: bool, done) -> None:
    """Run `items` (``[(index, input, Output)]``, largest first) on `jobs` spawned workers; `done(index, record)`
    as each ends. A worker that dies breaks the pool: the file it had begun (each worker says which file it
    begins, `_work`) fails with status 1, the others not done run on a new pool (at most `RESTARTS` times)."""
    import multiprocessing
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
    from concurrent.futures.process import BrokenProcessPool

    from ..io._place import remove_stale
    from ._interrupt import on_interrupt

    context = multiprocessing.get_context("spawn")
    pools = []

    def emergency():
        if pools:
            _stop(pools[-1], folder)
        return None

    with on_interrupt(emergency):
        for attempt in range(RESTARTS + 1):
            # all of it anew for each pool: a worker killed while it held the queue's lock would leave the next
            # pool's workers waiting for it forever, and a pid seen before may be a new worker's
            begun_queue, begun, procs = context.SimpleQueue(), {}, {}  # index -> pid of its worker; pid -> process
            pools.append(ProcessPoolExecutor(min(jobs, len(items)), mp_context=context, initializer=_start_worker,
                                             initargs=(begun_queue,)))
            pool, futures, lost = pools[-1], {}, []
            try:
                with _environment(worker_environment(jobs)):  # the workers start with the first files submitted
                    for index, src, out in items:
                        futures[pool.submit(_work, index, str(src), out, settings, debug)] = (index, src, out)
                pending = set(futures)
                while pending:
                    procs.update(getattr(pool, "_processes", None) or {})
                    finished, pending = wait(pending, timeout=POLL, return_when=FIRST_COMPLETED)
                    for f in finished:
                        try:
                            done(futures[f][0], f.result())
                        except BrokenProcessPool:
                            lost.append(futures[f])
                    if not finished:
                        done(None, None)
            except KeyboardInterrupt:
                _stop(pool, folder)
                pool.shutdown(wait=True)
                _release_queues()
                raise
            finally:
                pool.shutdown(wait=True, cancel_futures=True)
                remove_stale(folder)  # what a worker that died left (a live process's files are not touched)
            written = {}  # index -> identities of the targets its worker wrote
            while not begun_queue.empty():
                index, what = begun_queue.get()
                if isinstance(what, list):
                    written[index] = what
                else:
                    begun[index] = what
            died = [item for item in lost if _died(procs.get(begun.get(item[0])))]
            items = [_ours(item, written.get(item[0])) for item in lost if item not in died]
            for index, src, out in died:
                done(index, _failed(src, out.path, 1, f"{src}: the worker process smoothing it ended abruptly "
                                    f"({_ending(procs[begun[index]].exitcode)})"))
            if items and attempt == RESTARTS:
                for index, src, out in items:
                    done(index, _failed(src, out.path, 1, f"{src}: not smoothed: the worker processes ended "
                                        f"abruptly {RESTARTS + 1} times, each time with other files"))
            if not items or attempt == RESTARTS:
                return


def _ending(code: int) -> str:
    """How a worker ended (its exit code as `multiprocessing` gives it), for the error of the file it had begun."""
    if code >= 0:
        return f"exit status {code}"
    try:
        name = signal.Signals(-code).name
    except ValueError:
        return f"killed by signal {-code}"
    if -code == signal.SIGKILL:
        return "killed by SIGKILL: by a user, or by the kernel when memory ran out"
    crash = -code in (signal.SIGSEGV, signal.SIGBUS, signal.SIGABRT, signal.SIGILL, signal.SIGFPE)
    return f"killed by {name}" + (": a crash in native code" if crash else "")


def _ours(item, wrote: list | None):
    """A file to try again after its pool broke: ``(index, input, Output)`` with, where its worker had written it
    (`wrote`: the identities of the Output's targets then) and they are still those files, each of them allowed
    to be replaced (the worker wrote its output, and the pool broke before its record came back: the new run
    writes it again, where the check before it would otherwise find a file that appeared while it ran)."""
    import dataclasses

    from ..io._place import identity

    index, src, out = item
    if not wrote:
        return item
    allowed = dict(out.allowed)
    for target, was in zip(out.targets, wrote, strict=False):
        if was is not None and identity(target) == was:
            allowed[os.path.abspath(target)] = was
    return index, src, dataclasses.replace(out, allowed=allowed)


def _died(proc) -> bool:
    """Whether a worker that had begun a file ended of itself (killed, a crash), not stopped by its pool (SIGTERM,
    as the pool stops every worker once one has died)."""
    if proc is None:
        return False
    return proc.exitcode not in (None, -signal.SIGTERM, 128 + signal.SIGTERM)


def _release_queues() -> None:
    """Unlink the pool's semaphores now: an interrupted command ends without the exit handlers that would
    (`jaxci.cli.entry`), and multiprocessing's resource tracker would then warn of "leaked semaphore objects"."""
    import multiprocessing.util

    run = getattr(multiprocessing.util, "_run_finalizers", None)
    if run is not None:
        run(0)


# ------------------------------------------------------------------------------------------------- the batch
def run_batch(args) -> int:
    """``jaxci smooth IN... --out-dir DIR``: see the module docstring. Returns the exit status."""
    from ..errors import ConfigError, JaxciError
    from ..runtime.phases import listening
    from ..runtime.process import schedulable_cpus
    from ._files import check_output
    from ._progress import Display, wanted
    from ._smooth_file import smooth_options

    started = time.perf_counter()
    if args.report is not None:
        raise ConfigError("jaxci smooth: --report writes one file, so it cannot go with --out-dir (see jaxci "
                          "smooth --help)")
    if args.jobs is not None and args.jobs < 1:
        raise ConfigError(f"jaxci smooth: --jobs expects a positive number of worker processes, got {args.jobs}")
    settings = smooth_options(args)
    inputs = expand(args.paths)
    outputs = [Path(args.out_dir) / p.name for p in inputs]
    refuse_clashes(inputs, outputs)
    folder = _out_dir(args.out_dir)
    records: list[dict | None] = [None] * len(inputs)
    items = []
    for i, (src, dst) in enumerate(zip(inputs, outputs, strict=True)):
        try:
            items.append((i, src, check_output(dst, [src], force=args.force)))
        except JaxciError as e:
            records[i] = _failed(src, dst, 2, str(e))
    items.sort(key=lambda item: -_size(item[1]))  # the largest first: the last file to end is a small one
    jobs = max(1, min(args.jobs or schedulable_cpus(), len(items)))
    display = Display(live=wanted(args.quiet), started=started)
    ended = [0]

    def done(index, rec) -> None:
        if index is not None:
            records[index] = rec
            ended[0] += 1
            _say_failure(display, rec)
            if args.verbose:
                display.print(f"jaxci: {_row_line(rec)}")
        display.set_context(f"smooth: {ended[0]} of {len(items)} files done, {jobs} job{'s' * (jobs > 1)}")

    try:
        for rec in records:
            _say_failure(display, rec)
        done(None, None)
        if jobs == 1:
            with listening(display.on_event if display.live else None):
                for index, src, out in items:
                    done(index, smooth_one(str(src), out, settings, args.debug))
        else:
            _run_pool(items, settings, jobs, folder, args.debug, done)
    except KeyboardInterrupt:
        written = sum(1 for r in records if r is not None and r.get("exit_code") in (0, 3))
        raise KeyboardInterrupt(f"{written} of {len(inputs)} files written to {folder} (complete); the others "
                                f"not written") from None
    finally:
        display.close()
    code = max((r["exit_code"] for r in records), default=0)
    totals = {"files": len(records), "ok": sum(r["exit_code"] == 0 for r in records),
              "failed": sum(r["exit_code"] != 0 for r in records), "exit_code": code, "jobs": jobs,
              "out_dir": str(folder), "wall_seconds": time.perf_counter() - started}
    for rec in records:
        for w in rec["warnings"]:
            print(f"jaxci: warning: {Path(rec['input']).name}: {w}", file=sys.stderr)
        if args.debug and rec.get("traceback"):
            print(rec["traceback"], file=sys.stderr, end="")
    if args.json:
        import json

        print(json.dumps({"files": records, "totals": totals}))
    else:
        print(format_table(records, totals))
    return code


def _size(path: Path) -> int:
    try:
        return os.path.getsize(path)
    except OSError:
        return 0


def _say_failure(display, rec) -> None:
    """A failed file's line on stderr, as the single form prints it (its error names the file, else it is named)."""
    if rec is None or not rec.get("error"):
        return
    error = rec["error"]
    if rec["input"] not in error and rec["output"] not in error:
        error = f"{rec['input']}: {error}"
    kind = "" if error.startswith("internal error") or rec["exit_code"] == 3 else "error: "
    display.print(f"jaxci: {kind}{error}")


def _f(x) -> str:
    return "-" if x is None else f"{x:.6g}"


def _cells(rec: dict) -> tuple[str, str, str, str, str, str]:
    """name, hexahedra, worst before -> after, mean before -> after, seconds, status of one file's record."""
    b, a = rec.get("before"), rec.get("after")
    name = Path(rec["input"]).name
    hexes = "-" if b is None else str(b["n_elements"])
    worst = "-" if b is None else f"{_f(b['max_condition'])} -> {_f(a['max_condition'])}"
    mean = "-" if b is None else f"{_f(b['mean_condition'])} -> {_f(a['mean_condition'])}"
    status = "ok" if rec["exit_code"] == 0 else f"exit {rec['exit_code']}"
    return name, hexes, worst, mean, f"{rec['seconds']:.2f}", status


def _row_line(rec: dict) -> str:
    name, hexes, worst, mean, seconds, status = _cells(rec)
    if rec.get("before") is None:
        return f"{name}: {seconds} s, {status}"
    return f"{name}: {hexes} hexahedra, max k/3 {worst}, mean k/3 {mean}, {seconds} s, {status}"


def format_table(records: list[dict], totals: dict) -> str:
    """The batch's table: a row per file (in the order of the inputs) and the total line."""
    head = ("file", "hexahedra", "max k/3 before -> after", "mean k/3 before -> after", "seconds", "status")
    rows = [head, *(_cells(r) for r in records)]
    width = [max(len(r[k]) for r in rows) for k in range(len(head))]
    lines = ["  ".join(c.ljust(w) if k in (0, 2, 3, 5) else c.rjust(w)
                       for k, (c, w) in enumerate(zip(r, width, strict=True))).rstrip() for r in rows]
    failed = f", {totals['failed']} failed (exit status {totals['exit_code']})" if totals["failed"] else ""
    lines.append(f"total: {totals['ok']} of {totals['files']} files ok{failed}; {totals['jobs']} "
                 f"job{'s' * (totals['jobs'] > 1)}, {totals['wall_seconds']:.2f} s wall; outputs in "
                 f"{totals['out_dir']}")
    return "\n".join(lines)
