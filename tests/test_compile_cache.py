"""Compilation once per machine (`jaxci.runtime.compile_cache`, `jaxci.runtime._export`, `jaxci.runtime._keys`): where
the cache lives and how to turn it off, that importing jaxci changes no JAX setting, that a compiled entry point called
through its exported program gives what the jitted function gives, that a second fresh process at a size seen before
compiles nothing new, and that an unreadable entry is rewritten, never an error."""

from __future__ import annotations

import functools
import json
import os
import subprocess
import sys
import threading
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

from jaxci.optim.cohort import StaticParams
from jaxci.runtime import compile_cache
from jaxci.runtime._export import _dumps, exportable
from jaxci.runtime._keys import Keyer, Unkeyable
from jaxci.runtime._lazy import jit, pytree_dataclass
from jaxci.runtime.transfer import compile_totals, program

SRC = str(Path(__file__).resolve().parents[1] / "src")


# ------------------------------------------------------------------------------------------------- where
def test_the_folder_follows_the_environment(tmp_path):
    home = Path("~").expanduser()
    assert compile_cache.directory({}) == home / ".cache" / "jaxci" / "jax"
    assert compile_cache.directory({"XDG_CACHE_HOME": str(tmp_path)}) == tmp_path / "jaxci" / "jax"
    assert compile_cache.directory({"XDG_CACHE_HOME": "relative/dir"}) == home / ".cache" / "jaxci" / "jax"
    assert compile_cache.directory({"JAXCI_CACHE_DIR": str(tmp_path / "c"), "XDG_CACHE_HOME": "/x"}) == tmp_path / "c"
    assert compile_cache.directory({"JAXCI_CACHE_DIR": ""}) is None  # the one way to turn it off


def _child(code: str, env: dict, timeout: float = 600) -> dict:
    """Run `code` in a fresh interpreter with jaxci from this checkout; its last line of output, as JSON."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [SRC, os.environ.get("PYTHONPATH")])), **env}
    p = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=timeout)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-4000:]
    return json.loads(p.stdout.strip().splitlines()[-1])


def test_importing_jaxci_or_running_the_host_engine_changes_no_jax_setting(tmp_path):
    code = ("import json, jaxci; from jaxci.mesh.generate import perturb_box; "
            "jaxci.smooth(perturb_box(3, amplitude=0.2, seed=0), engine='host'); import jax; "
            "print(json.dumps([jax.config.jax_compilation_cache_dir, "
            "jax.config.jax_persistent_cache_min_compile_time_secs]))")
    out = _child(code, {"JAXCI_CACHE_DIR": str(tmp_path / "cache")})
    assert out == [None, 1.0]
    assert not (tmp_path / "cache").exists()


# ---------------------------------------------------------------------------------------------- the keys
def _f(x, a=1.0):
    return x * a


def test_keys_tell_apart_what_tracing_depends_on_and_refuse_what_they_cannot_key():
    key = Keyer()
    assert key((1, 2.0, "a", None)) == key((1, 2.0, "a", None))
    assert key(1.0) != key(1) != key(True)
    assert key(frozenset({"a", "b", "c"})) == key(frozenset({"c", "b", "a"}))
    assert key({"b": 1, "a": 2}) == key({"a": 2, "b": 1})
    assert key(functools.partial(_f, a=2.0)) != key(functools.partial(_f, a=3.0))

    def closure(v):
        return lambda x: x + v

    assert key(closure(1.0)) != key(closure(2.0)) and key(closure(1.0)) == key(closure(1.0))
    assert key(optx.LBFGS(rtol=1e-3, atol=1e-4)) != key(optx.LBFGS(rtol=1e-3, atol=1e-5))
    assert key(np.arange(4)) != key(np.arange(4) + 1)
    # a named tuple of static hyperparameters (CI's StaticParams) by its values: once keyed by its empty state,
    # a stored global CI program of 60 attempts ran when 1000 were asked for
    assert key(StaticParams(5, 5, 64, 256, True, 8)) != key(StaticParams(5, 5, 1024, 256, True, 8))
    assert key(StaticParams(5, 5, 64, 256, True, 8)) != key((5, 5, 64, 256, True, 8))
    for bad in (jnp.ones(3), threading.Lock(), np.zeros(1 << 17)):
        with pytest.raises(Unkeyable):
            key(bad)


def test_a_key_is_the_same_in_another_process():
    code = ("import inspect, json, optimistix as optx; from jaxci.runtime._keys import Keyer;"
            "from jaxci.optim._solve import solve_loop; from jaxci.optim.solver_objective import min_fn_closed as f;"
            "print(json.dumps([Keyer()(optx.LBFGS(rtol=1e-3, atol=1e-4)), Keyer()(f),"
            "Keyer()(inspect.unwrap(solve_loop))]))")
    first, second = _child(code, {}), _child(code, {})
    assert first == second


# ------------------------------------------------------------------------------------------ exported calls
@pytree_dataclass(static=("label",))
class _Out:
    value: object
    label: str


@jit(static_argnames=("power",))
def _toy(x, scale, power: int = 2, *, shift=0.0):
    return {"y": x ** power * scale + shift, "out": _Out(jnp.sum(x), f"p{power}")}


@eqx.filter_jit
def _toy_filter(x, solver, steps: int):
    return x * steps + solver.rtol, optx.RESULTS.successful, steps


def _same(a, b):
    la, ta = jax.tree_util.tree_flatten(a)
    lb, tb = jax.tree_util.tree_flatten(b)
    assert ta == tb
    for u, v in zip(la, lb, strict=True):
        if isinstance(u, jax.Array):
            assert u.dtype == v.dtype and np.array_equal(np.asarray(u), np.asarray(v))
            assert u.committed == v.committed  # as jit's: a later call compiles nothing for a committed input
        else:
            assert u == v


@pytest.mark.parametrize("fn,args,kwargs", [
    (_toy, (np.arange(6, dtype=np.float32), 1.5), {"power": 3, "shift": 2.0}),
    (_toy, (jnp.arange(4.0), 2), {}),
    (_toy_filter, (jnp.arange(5.0), optx.LBFGS(rtol=1e-3, atol=1e-4), 7), {}),
], ids=["jit-numpy-weak-scalars", "jit-device", "filter-jit-static-and-sentinel"])
def test_an_exported_program_gives_what_the_function_gives(tmp_path, fn, args, kwargs):
    with compile_cache.exporting_to(tmp_path):
        s0 = compile_cache.stats()
        first = exportable(fn)(*args, **kwargs)  # traced, exported, stored, run as exported
        s1 = compile_cache.stats()
        again = exportable(fn)(*args, **kwargs)  # a new wrapper (as a new process): read back
        s2 = compile_cache.stats()
    assert s1["exported"] == s0["exported"] + 1 and s2["loaded"] == s1["loaded"] + 1, (s0, s1, s2)
    assert s2["plain"] == s0["plain"]
    plain = fn(*args, **kwargs)
    _same(first, plain)
    _same(again, plain)
    assert list((tmp_path / "exported").glob("*.jxp"))
    assert not list((tmp_path / "exported").glob(".tmp-*"))


def test_another_shape_static_value_or_x64_mode_is_another_program(tmp_path):
    run = exportable(_toy)
    with compile_cache.exporting_to(tmp_path):
        run(jnp.arange(4.0), 1.0)
        run(jnp.arange(5.0), 1.0)
        run(jnp.arange(4.0), 1.0, power=3)
        with jax.enable_x64(False):
            run(np.arange(4.0, dtype=np.float32), 1.0)
        run(jnp.arange(4.0), 2.0)  # a traced scalar: the same program as the first
    assert len(list((tmp_path / "exported").glob("*.jxp"))) == 4


def test_an_unreadable_entry_is_rewritten_not_an_error(tmp_path):
    x = jnp.arange(3.0)
    with compile_cache.exporting_to(tmp_path):
        want = exportable(_toy)(x, 1.0)
        (entry,) = (tmp_path / "exported").glob("*.jxp")
        for garbage in (b"", b"not a pickle", entry.read_bytes()[: entry.stat().st_size // 2]):
            entry.write_bytes(garbage)
            s0 = compile_cache.stats()
            _same(exportable(_toy)(x, 1.0), want)
            s1 = compile_cache.stats()
            assert s1["discarded"] == s0["discarded"] + 1 and s1["exported"] == s0["exported"] + 1
            assert s1["loaded"] == s0["loaded"]
        s0 = compile_cache.stats()
        _same(exportable(_toy)(x, 1.0), want)  # the rewritten entry is good
        assert compile_cache.stats()["loaded"] == s0["loaded"] + 1


def test_a_program_stored_twice_in_one_process_loads_and_runs(tmp_path):
    """With JAX's persistent cache on (as in the suite, and in the jaxci command), a program stored a second time
    in one process (after its entry was spoilt, or in another cache folder) is compiled anew, not taken from JAX's
    cache: an executable served from there is serialized without some of its code, and loading it failed
    ("Function broadcast_multiply_fusion not found"). JAX's cache is on again afterwards."""
    from jax._src import compilation_cache as jcc

    assert jax.config.jax_compilation_cache_dir  # the suite's (conftest)
    x = jnp.arange(3.0)
    for folder in (tmp_path / "a", tmp_path / "b"):
        with compile_cache.exporting_to(folder):
            s0 = compile_cache.stats()
            _same(exportable(_toy)(x, 1.0), _toy(x, 1.0))  # stored
            _same(exportable(_toy)(x, 1.0), _toy(x, 1.0))  # loaded, run
            s1 = compile_cache.stats()
        assert (s1["exported"], s1["loaded"]) == (s0["exported"] + 1, s0["loaded"] + 1), (folder, s0, s1)
        assert (s1["discarded"], s1["plain"]) == (s0["discarded"], s0["plain"]), (folder, s1["reasons"])
    assert jcc.is_cache_used(jax.devices()[0].client)


def test_a_loaded_program_whose_first_run_fails_is_dropped_for_the_function(tmp_path, monkeypatch):
    """A stored program that loads but fails when it first runs (XLA:CPU's "Function wrapped_iota not found" of an
    executable serialized without some of its code came only then, from the asynchronous run) gives way to the
    function itself: the caller gets the function's result, the entry is removed (the next process stores it again)
    and the program is not run again in this process."""
    from jaxci.runtime import _export

    x = jnp.arange(3.0)
    want = _toy(x, 1.0)
    with compile_cache.exporting_to(tmp_path):
        exportable(_toy)(x, 1.0)  # stored
        (entry,) = (tmp_path / "exported").glob("*.jxp")
        runs, failing = [], set()

        def failing_run(compiled):  # the loaded executable, whose outputs fail when awaited (as an XLA run's error)
            def run(*dyn):
                out = compiled(*dyn)
                runs.append(1)
                failing.update(id(v) for v in out)
                return out
            return run

        def loaded(*args):
            prog = load(*args)
            prog.compiled = failing_run(prog.compiled)
            return prog

        def await_(tree, real=jax.block_until_ready):
            if any(id(v) in failing for v in jax.tree_util.tree_leaves(tree)):
                raise RuntimeError("INTERNAL: NOT_FOUND: Function wrapped_iota not found")
            return real(tree)

        load = _export._load
        monkeypatch.setattr(_export, "_load", loaded)
        monkeypatch.setattr(_export.jax, "block_until_ready", await_)
        run = exportable(_toy)  # a new wrapper: as a new process, it loads the entry
        s0 = compile_cache.stats()
        got = run(x, 1.0)
        s1 = compile_cache.stats()
        _same(got, want)
        assert runs == [1] and not entry.exists()
        assert s1["loaded"] == s0["loaded"] + 1 and s1["discarded"] == s0["discarded"] + 1
        assert "an exported program failed" in s1["reasons"]
        _same(run(x, 1.0), want)  # the function again: the program is not run a second time
        assert runs == [1] and compile_cache.stats()["loaded"] == s1["loaded"]


def test_what_cannot_be_keyed_runs_as_the_function(tmp_path):
    @jax.jit
    def closes_over_an_array(x):
        return x + table

    table = jnp.arange(3.0)

    def plain_python(x):
        return x + 1

    @functools.partial(jax.jit, donate_argnums=0)
    def donates(x):
        return x + 1

    with compile_cache.exporting_to(tmp_path):
        s0 = compile_cache.stats()
        assert np.array_equal(exportable(closes_over_an_array)(jnp.ones(3)), np.arange(3.0) + 1)
        assert exportable(plain_python)(1) == 2
        assert np.array_equal(exportable(donates)(jnp.ones(2)), [2.0, 2.0])
        s1 = compile_cache.stats()
    assert s1["plain"] == s0["plain"] + 3 and s1["exported"] == s0["exported"]
    assert not list((tmp_path / "exported").glob("*.jxp"))
    assert "a device array in a static argument or a closure" in s1["reasons"]


def test_with_the_cache_off_nothing_is_exported(tmp_path):
    with compile_cache.exporting_to(None):
        s0 = compile_cache.stats()
        _same(exportable(_toy)(jnp.arange(3.0), 1.0), _toy(jnp.arange(3.0), 1.0))
        assert compile_cache.stats() == s0


def test_a_program_is_timed_without_its_compilation(tmp_path):
    from jaxci.runtime.transfer import totals

    timed, x = program(_toy), jnp.arange(7.0)
    with compile_cache.exporting_to(tmp_path):
        c0, d0 = compile_totals(), totals()["device_s"]
        timed(x, 1.0)
        c1, d1 = compile_totals(), totals()["device_s"]
    assert c1["exported"] > c0["exported"] and c1["compiled"] == c0["compiled"] + 1
    compiling = sum(c1[k] - c0[k] for k in ("trace", "lower", "backend", "exported"))
    assert 0 <= d1 - d0 < compiling
    assert timed.lower(x, 1.0).compile().memory_analysis() is not None  # the jitted function's own AOT lowering


def test_sentinels_keep_their_identity_through_an_entry():
    import pickle

    tree = jax.tree_util.tree_structure(optx.RESULTS.successful)
    back = pickle.loads(_dumps({"tree": tree}))["tree"]
    assert back == tree and jax.tree_util.tree_unflatten(back, [jnp.int32(0)]) == optx.RESULTS.successful


def test_concurrent_writers_leave_whole_entries(tmp_path):
    datas = [bytes([i]) * 200_000 for i in range(4)]
    seen, errors = [], []
    with compile_cache.exporting_to(tmp_path):

        def write(d):
            for _ in range(5):
                compile_cache.write_entry("e.jxp", d)

        def read():
            for _ in range(50):
                path = tmp_path / "exported" / "e.jxp"
                if path.exists():
                    seen.append(path.read_bytes())

        threads = [threading.Thread(target=write, args=(d,)) for d in datas] + [threading.Thread(target=read)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    assert not errors and all(s in datas for s in seen)
    assert (tmp_path / "exported" / "e.jxp").read_bytes() in datas
    assert not list((tmp_path / "exported").glob(".tmp-*"))


# ------------------------------------------------------------------------------------- fresh processes
_SMOOTH = """
import json, hashlib, numpy as np, jaxci
from jaxci.runtime import compile_cache
from jaxci.mesh.generate import perturb_box
res = jaxci.smooth(perturb_box(6, amplitude=0.3, seed=2), "lbfgs", engine="jax", dtype="float64")
import jax
print(json.dumps({"points": hashlib.sha256(np.ascontiguousarray(res.mesh.points).tobytes()).hexdigest(),
                  "stats": compile_cache.stats(), "phases": res.phases["total"],
                  "jax_cache": jax.config.jax_compilation_cache_dir,
                  "thresholds": [jax.config.jax_persistent_cache_min_compile_time_secs,
                                 jax.config.jax_persistent_cache_min_entry_size_bytes]}))
"""


@pytest.mark.slow
def test_a_second_process_compiles_nothing_and_the_results_agree(tmp_path):
    """`jaxci.smooth` on the JAX engine in fresh processes with one cache folder: the first traces, exports and
    compiles; the second loads every program (nothing traced or compiled anew, under a second of compilation);
    after its entries are spoilt a third rewrites them and a fourth loads those; with ``JAXCI_CACHE_DIR=`` a fifth
    uses no cache at all (not the default folder either). All five give the same mesh, bit for bit."""
    cache = tmp_path / "cache"
    cold = _child(_SMOOTH, {"JAXCI_CACHE_DIR": str(cache)})
    warm = _child(_SMOOTH, {"JAXCI_CACHE_DIR": str(cache)})
    assert cold["stats"]["exported"] >= 1 and cold["stats"]["plain"] == 0, cold["stats"]
    assert cold["phases"]["compiled"] > cold["phases"]["cache_hits"]
    assert cold["jax_cache"] == str(cache) and cold["thresholds"] == [0.0, -1]  # small programs cached too
    assert warm["stats"]["loaded"] == cold["stats"]["exported"] and warm["stats"]["exported"] == 0, warm["stats"]
    assert warm["phases"]["compiled"] == warm["phases"]["cache_hits"], warm["phases"]  # nothing compiled anew
    assert warm["phases"]["compile_seconds"] < 1.0, warm["phases"]
    assert warm["points"] == cold["points"]

    entries = sorted((cache / "exported").glob("*.jxp"))
    assert len(entries) == cold["stats"]["exported"]
    for e in entries:
        e.write_bytes(e.read_bytes()[:100])
    spoilt = _child(_SMOOTH, {"JAXCI_CACHE_DIR": str(cache)})
    assert spoilt["stats"]["discarded"] == len(entries) and spoilt["stats"]["exported"] == len(entries)
    assert spoilt["points"] == cold["points"]
    # the programs it rewrote were compiled while JAX's own cache held them (an executable loaded from there and
    # stored failed when a later process ran it: "Function wrapped_iota not found"): they load and run
    again = _child(_SMOOTH, {"JAXCI_CACHE_DIR": str(cache)})
    assert again["stats"]["loaded"] == len(entries) and again["stats"]["discarded"] == 0, again["stats"]
    assert again["points"] == cold["points"]

    home = tmp_path / "home"
    off = _child(_SMOOTH, {"JAXCI_CACHE_DIR": "", "HOME": str(home), "XDG_CACHE_HOME": str(home / "xdg")})
    assert off["jax_cache"] is None and off["stats"] == {"loaded": 0, "exported": 0, "discarded": 0, "plain": 0,
                                                          "reasons": {}}
    assert off["phases"]["cache_hits"] == 0 and not home.exists()
    assert off["points"] == cold["points"]


def test_the_package_hash_covers_every_folder_of_jaxci(monkeypatch):
    """`package_hash` (part of every key) reads jaxci's own files from the package root, not from the folder of
    `jaxci.runtime._keys`: a change to the interface, a model module or the C kernels makes new keys too."""
    from jaxci.runtime import _keys

    read = []
    monkeypatch.setattr(_keys, "_file_hash", lambda path: read.append(Path(path)) or "0")
    _keys.package_hash.__wrapped__()
    root = Path(_keys.__file__).resolve().parents[1]
    names = {p.relative_to(root).as_posix() for p in read}
    assert {"__init__.py", "native.py", "_ckernels.c", "interface/smooth.py", "mesh/generate.py",
            "runtime/_keys.py"} <= names, sorted(names)
