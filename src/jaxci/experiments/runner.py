"""`jaxci.experiments.runner`: smoothing experiments run and recorded.

`run_experiment` smooths every (mesh, method, seed) of an `Experiment` (a YAML config read and validated by
`jaxci.experiments.config.load_config`, re-exported here; the config format is described in `jaxci.experiments.config`)
with `jaxci.interface.smooth.smooth` and writes one output folder. The output folder is checked before anything runs
(`jaxci.experiments.results.stage`): one that exists (without ``force``), that is not a jaxci results folder (with
``force``: a folder is replaced only if it holds earlier jaxci results and nothing else), that holds an input or
the current folder, or that cannot be written is a `jaxci.errors.ConfigError`, as is ``device: gpu`` on a
machine with no GPU.

Output folder (written to a temporary sibling folder, renamed into place at the end; every file via a
temporary file and `os.replace`): ``summary.json``, ``runs.csv``, ``history.json``, ``report.md`` (the paper's
Tables 1-3 beside ours, `jaxci.experiments.report`), ``figures/*.png`` (`jaxci.experiments.plots`), ``meshes/*.vtu`` and
the marker ``.jaxci-results`` (`jaxci.experiments.results.MARKER`). A `KeyboardInterrupt` keeps the finished runs: the
folder is still written, with ``"partial": true`` and no figures (so that an interrupt acts at once); earlier results
are replaced only by a complete run (a partial one, or one where every run failed, goes beside them,
``<out>.partial-N`` / ``<out>.failed-N``). A run that fails (a `JaxciError` such as an inverted mesh with no
untangling, or an unexpected exception unless ``strict``) is recorded with its message and the other runs go
on.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import threading
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml

from ..errors import ConfigError, JaxciError
from .config import MAX_RUNS, Experiment, ResolvedMesh, ResolvedMethod
from .config import load_config as load_config  # re-exported: ``from jaxci.experiments.runner import load_config``
from .config_errors import Locator
from .report import RunRecord, json_ready, write_vtus
from .results import Staged, stage, write_text


@dataclasses.dataclass(frozen=True)
class ExperimentResult:
    """What `run_experiment` returns: the output folder, the run records, the summary, whether it is partial."""

    out: Path
    records: tuple[RunRecord, ...]
    summary: dict
    partial: bool
    #: the earlier results folder left as it was, when this run was partial or every run failed (`out` is then
    #: a sibling of it, ``<kept>.partial-N`` or ``<kept>.failed-N``), or when the folder asked for appeared or
    #: changed while the experiment ran (`taken`; `out` is ``<kept>.new-N``); None when `out` is the folder asked for
    kept: Path | None = None
    #: why the results are not in the folder asked for although they could have replaced it: it appeared, or
    #: changed, while the experiment ran (`jaxci.experiments.results.Staged.taken`); else None
    taken: str | None = None

    @property
    def failed(self) -> list[RunRecord]:
        return [r for r in self.records if r.status != "ok"]


def check_device(exp: Experiment) -> None:
    """`ConfigError` naming the config when it asks for ``device: gpu`` and JAX sees no accelerator (before
    anything runs); ``cpu`` and ``auto`` always hold (`jaxci.interface.engine`)."""
    from ..interface.engine import accelerator, no_accelerator_message

    if exp.config.device == "gpu" and accelerator() is None:
        line = Locator(exp.path, yaml.compose(exp.path.read_text(), Loader=yaml.SafeLoader)).line(("device",))
        raise ConfigError(f"{exp.path}:{line}: {no_accelerator_message('device: gpu')}")


def resolve_output(exp: Experiment, out: str | os.PathLike | None) -> tuple[Path, str]:
    """The output folder and the name of the setting it came from (``--out``, ``output`` or the default)."""
    if out is not None:
        return Path(out), "--out"
    if exp.config.output is not None:
        line = Locator(exp.path, yaml.compose(exp.path.read_text(), Loader=yaml.SafeLoader)).line(("output",))
        return Path(exp.config.output), f"{exp.path}:{line}: output"
    return Path("results") / exp.path.stem, "output (default)"


def run_experiment(
    exp: Experiment,
    out: str | os.PathLike | None = None,
    *,
    force: bool = False,
    seeds: int | None = None,
    progress: Callable[[int, int, str], None] | None = None,
    strict: bool = False,
    on_start: Callable[[Callable[[], ExperimentResult | None]], None] | None = None,
) -> ExperimentResult:
    """Run every (mesh, method, seed) of `exp` and write the output folder.

    **Arguments:**

    - `exp`: a loaded `Experiment` (`load_config`).
    - `out`: the output folder (default: the config's ``output``, else ``results/<config stem>``). Keyword
      arguments below are keyword only.
    - `force`: replace an existing output folder, only if it holds earlier jaxci results and nothing else, and
      only once the new run is complete (`jaxci.experiments.results`).
    - `seeds`: run seeds ``0..seeds-1`` instead of the config's.
    - `progress`: called as ``progress(done, total, description)`` before each run and once at the end.
    - `strict`: re-raise an unexpected exception of a run (a bug) instead of recording it as a failed run.
    - `on_start`: called once the output folder is checked, as ``on_start(finish)``; ``finish()`` may be called
      from another thread (the jaxci command's interrupt watchdog, while this thread is stuck in a long XLA
      call): it writes the finished runs as a partial result (no figures) and returns its `ExperimentResult`,
      the result already written, or None if it could not get hold of the output within 10 s.
      ``finish(write=False)`` only returns the result already written, or None (the command, when an interrupt
      comes as `run_experiment` returns).

    **Returns:** an `ExperimentResult`. A run that raises a `JaxciError` (e.g. an inverted mesh that cannot be
    untangled) is recorded as ``"failed"`` and the others go on. On `KeyboardInterrupt` the finished runs are
    written with ``"partial": true`` (no figures) and a `KeyboardInterrupt` is raised again, with the
    `ExperimentResult` as its argument. Earlier results in `out` are kept when the run is partial or every run
    failed: the new results then go beside them (``<out>.partial-N`` / ``<out>.failed-N``,
    `ExperimentResult.kept`).
    """
    if seeds is not None:
        if isinstance(seeds, bool) or int(seeds) != seeds or not 1 <= seeds <= MAX_RUNS:
            raise ConfigError(f"--seeds must be an integer in [1, {MAX_RUNS}], got {seeds}")
        exp = dataclasses.replace(exp, seeds=tuple(range(int(seeds))))
    check_device(exp)
    out_path, key = resolve_output(exp, out)
    files = [exp.path, *(m.path for m in exp.meshes if m.path is not None),  # with what was read through them
             *(f for m in exp.meshes if m.mesh is not None for f in m.mesh.input_files)]
    state = _Run(exp, stage(out_path, key, force, files))
    if on_start is not None:
        on_start(state.abort)
    partial = False
    try:
        plan = exp.runs()
        state.total = len(plan)
        inputs: dict[tuple[str, int], Any] = {}
        done = 0
        try:
            for rm, seeds, meth in _work(exp, plan):
                if progress is not None:
                    what = f"seed {seeds[0]}" if len(seeds) == 1 else f"{len(seeds)} seeds together"
                    progress(done, len(plan), f"{rm.name} / {meth.label} / {what}")
                for rec, mesh, res in _runs(exp, rm, seeds, meth, inputs, strict):
                    if res is not None and rec.seed == exp.seeds[0]:
                        state.results[(rm.name, meth.label)] = (mesh, res)
                        if exp.config.write_meshes:
                            rec.mesh_file = write_vtus(state.staged.tmp, rm, meth, rec.seed, mesh, res)
                    state.records.append(rec)
                done += len(seeds)
                inputs = {kk: v for kk, v in inputs.items() if kk == (rm.name, seeds[-1])}  # one mesh in memory
        except KeyboardInterrupt:  # keep the finished runs; written below, marked partial
            partial = True
        if progress is not None:
            progress(len(state.records), len(plan), "writing results")
    except BaseException:
        state.staged.discard()
        raise
    return state.finish(partial)


class _Run:
    """The state of one `run_experiment` call that its output needs: written by `finish` (this thread) or by
    `abort` (another thread, on an interrupt), whichever comes first, under `lock`."""

    def __init__(self, exp: Experiment, staged: Staged):
        self.exp, self.staged = exp, staged
        self.records: list[RunRecord] = []
        self.results: dict[tuple[str, str], Any] = {}  # first seed's (input mesh, SmoothResult) per (mesh, label)
        self.total = 0
        self.t0 = time.perf_counter()
        self.lock = threading.Lock()
        self.result: ExperimentResult | None = None
        self.summary: dict = {}

    def finish(self, partial: bool) -> ExperimentResult:
        """Write the results (with figures); on a `KeyboardInterrupt` meanwhile, write them as partial without
        figures. Raises `KeyboardInterrupt(result)` when interrupted (`partial`, or during the writing)."""
        interrupted = partial
        with self.lock:
            if self.result is not None:  # `abort` wrote them
                interrupted = True
            else:
                try:
                    self.result = self._write(partial, figures=self.exp.config.figures and not partial)
                except KeyboardInterrupt:
                    interrupted = True
                    if self.staged.committed is not None:  # interrupted just after the results were moved in
                        self.result = self._result(self.staged.committed, partial, self.summary)
                    else:  # figures may be half drawn: the runs without them
                        shutil.rmtree(self.staged.tmp / "figures", ignore_errors=True)
                        self.result = self._write(True, figures=False)
                except BaseException:
                    self.staged.discard()
                    raise
        if interrupted:
            raise KeyboardInterrupt(self.result)
        return self.result

    def abort(self, write: bool = True) -> ExperimentResult | None:
        """From another thread: write the finished runs as a partial result (no figures) unless done; returns the
        result written. `write` False: only the result already written, or None (nothing is written)."""
        if not self.lock.acquire(timeout=10.0):
            return None
        try:
            if self.result is None and write:
                self.result = self._write(True, figures=False)
            return self.result
        finally:
            self.lock.release()

    def _write(self, partial: bool, figures: bool) -> ExperimentResult:
        from . import plots, report

        exp, records = self.exp, list(self.records)
        tmp = self.staged.tmp
        summary = report.build_summary(exp, records, partial=partial, total_runs=self.total,
                                       elapsed=time.perf_counter() - self.t0)
        if figures:
            try:
                summary["figures"] = plots.write_figures(tmp / "figures", exp, records, self.results)
            except Exception as e:  # a plotting failure must not lose the runs: recorded, warned
                summary["figures"] = {"error": f"{type(e).__name__}: {e}"}
                warnings.warn(f"figures could not be drawn ({type(e).__name__}: {e}); the runs are written",
                              stacklevel=3)
        write_text(tmp / "summary.json", json.dumps(json_ready(summary), indent=1, allow_nan=False) + "\n")
        write_text(tmp / "history.json", json.dumps(json_ready(
            [{"mesh": r.mesh, "method": r.label, "seed": r.seed, **(r.history or {})} for r in records]),
            allow_nan=False) + "\n")
        write_text(tmp / "runs.csv", report.runs_csv(records))
        write_text(tmp / "report.md", report.render_report(summary))
        self.summary = summary
        complete = not partial and any(r.status == "ok" for r in records)
        return self._result(self.staged.commit(complete=complete, partial=partial), partial, summary, records)

    def _result(self, dest: Path, partial: bool, summary: dict, records=None) -> ExperimentResult:
        kept = self.staged.out if dest != self.staged.out else None
        return ExperimentResult(dest, tuple(self.records if records is None else records), summary, partial, kept,
                                self.staged.taken)


def _work(exp: Experiment, plan):
    """The runs of `plan` as work items ``(mesh, seeds, method)`` in plan order: global CI with several seeds of
    one mesh as one item (the first seed's place; `jaxci.interface.seeds.smooth_seeds` batches it), every other run
    alone."""
    batched = len(exp.seeds) > 1 and exp.config.batch_seeds
    seen = set()
    for rm, seed, meth in plan:
        if batched and meth.method == "ci-global":
            if (rm.name, meth.label) not in seen:
                seen.add((rm.name, meth.label))
                yield rm, tuple(s for m, s, mm in plan if m is rm and mm is meth), meth
        else:
            yield rm, (seed,), meth


def _runs(exp: Experiment, rm: ResolvedMesh, seeds: tuple, meth: ResolvedMethod, inputs: dict, strict: bool):
    """Smooth `rm` with `meth` for `seeds` (`jaxci.interface.seeds.iter_smooth_seeds`: global CI's seeds as one program
    where it can); yields ``(RunRecord, input mesh, SmoothResult or None)`` per seed as each ends (an interrupt
    keeps those that ended). A seed's failure (its mesh, its run) is its own; with `strict` a failure that is not a
    `JaxciError` (a bug) is raised."""
    from ..interface.seeds import iter_smooth_seeds

    b = rm.boundary
    kwargs = dict(dtype=exp.config.dtype, feature_angle=b.feature_angle, fix_boundary=b.fix_boundary,
                  fixed_nodes=b.fixed_nodes or None, fixed_sets=b.fixed_sets, untangle=exp.config.untangle,
                  engine=meth.engine, device=exp.config.device, **meth.params)
    meshes = {}
    for seed in seeds:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                if (rm.name, seed) not in inputs:
                    inputs[(rm.name, seed)] = rm.build(seed)
                meshes[seed] = inputs[(rm.name, seed)]
            except Exception as e:  # this seed's mesh: its failure alone
                if strict and not isinstance(e, JaxciError):
                    raise
                yield _record(rm, seed, meth, e, _messages(caught)), None, None
    ok = [s for s in seeds if s in meshes]
    if len(ok) == 1:  # one seed: `jaxci.smooth` itself (run inside the loop's warning capture)
        runs = (_one(meshes[s], meth.method, s, kwargs) for s in ok)
    else:
        runs = iter_smooth_seeds([meshes[s] for s in ok], meth.method, ok, errors="return", **kwargs)
    while True:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                i, res = next(runs)
            except StopIteration:
                return
            except JaxciError as e:  # the group's arguments (every seed's): each seed's failure
                for s in ok:
                    yield _record(rm, s, meth, e, _messages(caught)), meshes[s], None
                return
        if strict and isinstance(res, Exception) and not isinstance(res, JaxciError):
            raise res
        seed = ok[i]
        yield _record(rm, seed, meth, res, _messages(caught)), meshes[seed], (
            None if isinstance(res, BaseException) else res)


def _one(mesh, method: str, seed: int, kwargs: dict) -> tuple:
    """``(0, result)`` of `jaxci.smooth` on one seed: its `SmoothResult`, or the exception that ended it."""
    from ..interface.smooth import smooth

    try:
        return 0, smooth(mesh, method, seed=seed, **kwargs)
    except Exception as e:  # noqa: BLE001 - the run's failure, recorded (strict: raised by the caller)
        return 0, e


def _messages(caught) -> list:
    return list(dict.fromkeys(str(w.message) for w in caught))


def _record(rm: ResolvedMesh, seed: int, meth: ResolvedMethod, res, warned: list) -> RunRecord:
    """The `RunRecord` of one run: its `SmoothResult`, or the exception that ended it."""
    rec = RunRecord(mesh=rm.name, label=meth.label, method=meth.method, seed=seed, status="failed", notes=warned)
    if isinstance(res, JaxciError):
        rec.error = str(res)
        return rec
    if isinstance(res, BaseException):
        rec.error = (f"internal error ({type(res).__name__}: {res}); rerun with `jaxci --debug run` for the "
                     f"traceback")
        return rec
    rec.status = "ok"
    rec.iterations = int(res.iterations)
    rec.wall_time = float(res.wall_time)
    rec.before, rec.after = res.before.to_dict(), res.after.to_dict()
    rec.engine = None if res.plan is None else res.plan.to_dict()
    rec.notes = list(dict.fromkeys([*warned, *res.notes]))
    rec.history = {k: v for k, v in res.history.items() if k in ("objective", "max_condition", "best", "worst")}
    return rec
