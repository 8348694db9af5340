"""Several seeds of one smoothing: `smooth_seeds` and `iter_smooth_seeds`, global CI's seeds as ONE program.

`jaxci.smooth` is a generator underneath (`jaxci.interface.smooth.smooth_steps`): it validates, reports, untangles and
sets up, then yields the method's run (`jaxci.interface.smooth.MethodRun`) and takes its output back for the checks.
Here each seed's generator is taken to its method run in turn: global CI on the JAX engine (one device, a hexahedral
mesh) waits there for the others, every other run goes on to its end at once. The waiting seeds whose parameters, plan,
connectivity and parametrisation shapes agree run as one batched program (`jaxci.optim.global_ci.
global_ci_batched`: one compilation, one launch; each seed's mesh is the one it gets alone); any other runs alone.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator

import numpy as np

from ..errors import ConfigError
from ..runtime._lazy import jax
from .methods import MethodRun, free_scale, global_parametrisation, method_params
from .smooth import SmoothResult, smooth_steps


def smooth_seeds(meshes, method: str, seeds, *, errors: str = "raise", **kwargs) -> list:
    """`jaxci.smooth` of ``meshes[i]`` with ``seeds[i]`` for every i, where possible as ONE program: global CI
    (``"ci-global"``) on the JAX engine runs every seed's cohort in one batched program, from
    `jaxci.interface.engine.BATCH_SEEDS_FROM` seeds also under ``engine="auto"``. The meshes may differ (the paper's
    cubes are perturbed by the seed) but must share connectivity and boundary classes to be batched; seeds that cannot
    join the batch (an inverted input untangled first on another engine, nothing to move, another plan) and every
    other method run one after the other, as `jaxci.smooth` runs them.

    **Arguments:** `meshes` one `HexMesh` per seed (the same object may repeat); `method`; `seeds` the seeds;
    `errors`: ``"raise"`` (the first exception of a seed is raised) or ``"return"`` (it takes the place of that
    seed's result, the others go on); `**kwargs`: `jaxci.smooth`'s other arguments (`clock` excepted: each seed
    has its own).

    **Returns:** one `SmoothResult` (or exception) per seed, in order; a batched one has a note saying so and its
    equal share of the batch's time in its ``smooth`` phase and wall time.
    """
    results: list = [None] * len(seeds)
    for i, res in iter_smooth_seeds(meshes, method, seeds, errors=errors, **kwargs):
        results[i] = res
    return results


def iter_smooth_seeds(meshes, method: str, seeds, *, errors: str = "raise", **kwargs) -> Iterator[tuple]:
    """`smooth_seeds` as it goes: yields ``(index, result or exception)`` as each seed ends (a caller that is
    interrupted keeps the seeds that ended)."""
    from ..runtime.phases import PhaseClock

    if len(meshes) != len(seeds):
        raise ConfigError(f"smooth_seeds: {len(meshes)} meshes for {len(seeds)} seeds")
    if errors not in ("raise", "return"):
        raise ConfigError(f"smooth_seeds: errors must be 'raise' or 'return', got {errors!r}")
    kwargs.pop("clock", None)
    waiting: dict = {}  # index -> (generator, MethodRun): global CI on the JAX engine, for the batch
    for i, (mesh, seed) in enumerate(zip(meshes, seeds, strict=True)):
        steps = smooth_steps(mesh, method, seed=seed, clock=PhaseClock(), seeds=len(seeds), **kwargs)
        out = _step(steps, None, errors)
        if isinstance(out, MethodRun) and _may_batch(out):
            waiting[i] = (steps, out)
        elif isinstance(out, MethodRun):
            yield i, _finish(steps, out, None, errors)
        else:
            yield i, out
    batch, pars = _batchable({i: req for i, (_, req) in waiting.items()})
    outputs: dict = {}
    if batch:
        try:
            outputs = _run_batch({i: waiting[i][1] for i in batch}, pars)
        except Exception as e:  # noqa: BLE001 - the batch's failure is each of its seeds' (errors="return")
            if errors == "raise":
                raise
            outputs = {i: e for i in batch}
    for i, (steps, req) in waiting.items():
        res = _finish(steps, req, outputs.get(i), errors)
        if isinstance(res, SmoothResult):  # its wall time: its own phases (it waited while the others ran)
            own = sum(v["seconds"] for k, v in res.phases.items() if k not in ("total", "validate"))
            res = dataclasses.replace(res, wall_time=own)
        yield i, res


def _finish(steps, req: MethodRun, out, errors: str):
    """The result (or exception) of a seed whose method run is `req`: its output `out` (from the batch: an
    output or the batch's exception), else the method run alone now, sent to `steps` for the checks."""
    if out is None:
        try:
            out = req.run()
        except Exception as e:  # noqa: BLE001 - the seed's own failure (errors="return")
            if errors == "raise":
                raise
            return e
    if isinstance(out, Exception):
        return out
    return _step(steps, out, errors, finish=True)


def _step(steps, sent, errors: str, finish: bool = False):
    """Advance `steps` (sending `sent`): the `MethodRun` it yields, its result when it ends, or the exception it
    raised (``errors="return"``). With `finish` (the method's output sent) it must end."""
    try:
        out = next(steps) if sent is None else steps.send(sent)
        if finish:
            raise RuntimeError("the smoothing asked for a second method run")
        return out
    except StopIteration as done:
        return done.value
    except Exception as e:  # noqa: BLE001 - one seed's failure, not the others' (errors="return")
        if errors == "raise":
            raise
        return e


def _may_batch(req: MethodRun) -> bool:
    """Whether `req` can join a batch: global CI on the JAX engine, one device, a hexahedral mesh."""
    p = req.problem
    return req.method == "ci-global" and p.plan.engine == "jax" and p.devices is None and p.extra is None


def _batchable(asked: dict) -> tuple[list, list]:
    """The seeds of `asked` (index -> `MethodRun`, all `_may_batch`) that run as one batched program, those with
    the first one's parameters, plan, connectivity and parametrisation shapes (none if fewer than two), and their
    parametrisations (`jaxci.interface.methods.global_parametrisation`)."""
    from ..optim.global_ci import stackable

    if len(asked) < 2:
        return [], []
    first = next(iter(asked.values()))
    same = [i for i, r in asked.items() if r.params == first.params and r.problem.plan == first.problem.plan
            and np.array_equal(np.asarray(r.problem.conn), np.asarray(first.problem.conn))]
    if len(same) < 2:
        return [], []
    with first.context():
        pars = [global_parametrisation(asked[i].problem) for i in same]
    return (same, pars) if stackable(pars) else ([], [])


def _run_batch(runs: dict, pars: list) -> dict:
    """Global CI of the `MethodRun` values of `runs` (index -> run; `pars` their parametrisations) as one batched
    program; each run's clock gets an equal share of the batch's time (and compilation) in its ``smooth`` phase.
    Returns index -> `run_method`'s output, its resolved parameters with ``batched_seeds`` (how many ran together)."""
    from ..optim.global_ci import global_ci_batched
    from ..runtime.phases import PhaseClock

    reqs = list(runs.values())
    first = reqs[0]
    p = method_params("ci-global", first.params)
    clock = PhaseClock()
    with first.context(), clock.phase("batch"):
        keys = [jax.random.key(r.seed, impl="rbg") for r in reqs]
        out = global_ci_batched(keys, pars, first.problem.conn, [free_scale(r.problem) for r in reqs], p)
        out = [(np.asarray(x), it, hist) for x, it, hist in out]
    rec, n = clock.as_dict()["batch"], len(reqs)
    for r in reqs:
        r.clock.add("smooth", rec["seconds"] / n, rec["compile_seconds"] / n, device_s=rec["device_s"] / n)
    return {i: (x, it, hist, {**dataclasses.asdict(p), "batched_seeds": n})
            for i, (x, it, hist) in zip(runs, out, strict=True)}

