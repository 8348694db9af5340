"""`jaxci.experiments.config`: experiment configs in YAML, their schema, validated up front and loaded.

A config names meshes, methods and seeds; `load_config` reads and checks it into an `Experiment`, which
`jaxci.experiments.runner.run_experiment` runs. Example (every key shown; only `mesh` and `methods` are required):

```yaml
description: the paper's 27-element cube
mesh:                                  # one entry or a list
  - generate: {case: cube27}           # a paper cube (jaxci.mesh.generate.PAPER_CASES), perturbed by the run seed
  - name: block
    generate: {box: [10, 10, 10], amplitude: 0.3, which: sliding, size: [1, 1, 1]}   # optional seed: fixed
  - file: ../../shared/data/mesquite/1000hex-block-internal-bias.vtk   # relative to this file's folder
    boundary: {fix_boundary: true}     # per-mesh override of the top-level boundary
boundary: {feature_angle: 40, fix_boundary: false, fixed_sets: [], fixed_nodes: []}
methods:
  - {name: CI local, method: ci, params: {max_sweeps: 50}}
  - {name: CI global, method: ci-global, params: {attempts: 500}, meshes: [cube27]}   # meshes: restrict
  - {name: L-BFGS (JAX), method: lbfgs, engine: jax}   # engine: auto (default) | host | jax (jaxci.interface.engine)
seeds: [0, 1, 2]                       # or runs: N (seeds 0..N-1); default [0]
dtype: float32                         # float32 | float64: the JAX engine's (the host engine is float64)
device: auto                           # auto (default: an accelerator where JAX sees one) | cpu | gpu
batch_seeds: true                      # global CI: the seeds of a mesh as one batched program (jaxci.smooth_seeds)
output: results/cube27                 # relative to the working directory; default results/<config stem>
untangle: auto                         # auto | always | never
write_meshes: true                     # smoothed VTU of the FIRST seed of each (mesh, method) only
figures: true
report: {table1: {mesh: cube27, stage2: CI global}}   # Table 1 columns: method labels for stage 1 / stage 2
```

Every key is checked before anything runs or is written: unknown keys, wrong types, unknown methods, bad
method parameters (by constructing the method's parameter dataclass), missing mesh files. Each problem is ONE
`jaxci.errors.ConfigError` naming the file, the line and the key path, e.g.
``paper.yaml:14: methods[0].params.cohort: ...``.

This module knows nothing of running: `jaxci.experiments.runner` imports it, never the reverse.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import re
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from ..cells import EXTRA_TYPES
from ..errors import ConfigError, JaxciError
from ..mesh.generate import MAX_SEED
from .config_errors import Locator, check_duplicates, pydantic_message

#: Most runs (seeds) of one config.
MAX_RUNS = 100_000

# ----------------------------------------------------------------------------------------------- schema


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)


class GenerateSpec(_Model):
    """A generated mesh: one of the paper's cubes (`case`) or a perturbed box (`box` and the keys after it)."""

    case: str | None = None
    box: list[int] | None = None
    amplitude: float = 0.3
    which: Literal["sliding", "interior"] = "sliding"
    size: list[float] = Field(default_factory=lambda: [1.0, 1.0, 1.0])
    seed: int | None = None

    @model_validator(mode="after")
    def _values(self):
        from ..mesh.generate import PAPER_CASES

        if self.case is not None and self.case not in PAPER_CASES:
            raise ValueError(f"case: unknown case {self.case!r}; choose one of {', '.join(PAPER_CASES)}")
        if self.box is not None and (len(self.box) != 3 or min(self.box) < 1):
            raise ValueError(f"box: must be three element counts >= 1, [nx, ny, nz], got {self.box}")
        if len(self.size) != 3 or not all(0 < v < math.inf for v in self.size):
            raise ValueError(f"size: must be three positive finite edge lengths, got {self.size}")
        if not 0 <= self.amplitude <= 10:
            raise ValueError(f"amplitude: must be in [0, 10] (a fraction of the grid spacing), got {self.amplitude}")
        if self.seed is not None and not 0 <= self.seed <= MAX_SEED:
            raise ValueError(f"seed: must be an integer in [0, 2**32 - 1], got {self.seed}")
        if (self.case is None) == (self.box is None):
            raise ValueError("give exactly one of 'case' (a paper cube) or 'box' ([nx, ny, nz])")
        extra = {"amplitude", "which", "size"} & self.model_fields_set
        if self.case is not None and extra:
            raise ValueError(f"{', '.join(sorted(extra))}: only for 'box' (a paper case has its own perturbation)")
        return self


class BoundarySpec(_Model):
    """How boundary nodes may move (the keyword arguments of `jaxci.interface.smooth.smooth` of the same names)."""

    feature_angle: float = 40.0
    fix_boundary: bool = False
    fixed_sets: list[str] = Field(default_factory=list)
    fixed_nodes: list[int] = Field(default_factory=list)

    @field_validator("feature_angle")
    @classmethod
    def _angle(cls, v):
        if not 0 < v < 180:
            raise ValueError(f"feature_angle must be in degrees strictly between 0 and 180, got {v}")
        return v


class MeshSpec(_Model):
    """One mesh: ``file`` (a path, relative to the config's folder) or ``generate``; optional `name`, `boundary`."""

    name: str | None = None
    file: str | None = None
    generate: GenerateSpec | None = None
    boundary: BoundarySpec | None = None

    @model_validator(mode="after")
    def _one_source(self):
        if (self.file is None) == (self.generate is None):
            raise ValueError("give exactly one of 'file' or 'generate'")
        return self


class MethodSpec(_Model):
    """One method entry: a `name` (label, default the method), a `method` of `jaxci.interface.smooth.METHODS`, `params`,
    the `engine` it runs on (`jaxci.interface.engine.ENGINES`), the `meshes` it runs on (default all)."""

    name: str | None = None
    method: str
    params: dict[str, Any] = Field(default_factory=dict)
    engine: Literal["auto", "host", "jax"] = "auto"
    meshes: list[str] | None = None


class Table1Spec(_Model):
    """Which mesh and which two method labels fill the paper's Table 1 columns 'stage 1' and 'stage 2'."""

    mesh: str | None = None
    stage1: str | None = None
    stage2: str | None = None


class ReportSpec(_Model):
    table1: Table1Spec = Field(default_factory=Table1Spec)


class ExperimentConfig(_Model):
    """The whole YAML document (see the module docstring)."""

    description: str = ""
    mesh: list[MeshSpec]
    boundary: BoundarySpec = Field(default_factory=BoundarySpec)
    methods: list[MethodSpec] = Field(min_length=1)
    seeds: list[int] | None = None
    runs: int | None = None
    dtype: Literal["float32", "float64"] = "float32"
    device: Literal["cpu", "gpu", "auto"] = "auto"
    batch_seeds: bool = True
    output: str | None = None
    untangle: Literal["auto", "always", "never"] = "auto"
    write_meshes: bool = True
    figures: bool = True
    report: ReportSpec = Field(default_factory=ReportSpec)

    @field_validator("mesh", mode="before")
    @classmethod
    def _one_or_many(cls, v):
        return [v] if isinstance(v, dict) else v

    @field_validator("mesh")
    @classmethod
    def _not_empty(cls, v):
        if not v:
            raise ValueError("give at least one mesh")
        return v

    @field_validator("runs")
    @classmethod
    def _runs(cls, v):
        if v is not None and not 1 <= v <= MAX_RUNS:
            raise ValueError(f"runs must be in [1, {MAX_RUNS}], got {v}")
        return v

    @field_validator("seeds")
    @classmethod
    def _seeds(cls, v):
        if v is not None:
            if not v:
                raise ValueError("seeds must not be empty")
            if min(v) < 0 or max(v) > MAX_SEED or len(set(v)) != len(v):
                bad = [s for s in v if not 0 <= s <= MAX_SEED][:3] or v
                raise ValueError(f"seeds must be distinct integers in [0, 2**32 - 1], got {bad}")
            if len(v) > MAX_RUNS:
                raise ValueError(f"at most {MAX_RUNS} seeds, got {len(v)}")
        return v

    @model_validator(mode="after")
    def _seeds_or_runs(self):
        if self.seeds is not None and self.runs is not None:
            raise ValueError("give 'seeds' or 'runs', not both")
        return self


# ----------------------------------------------------------------------------------------------- loading


@dataclasses.dataclass(frozen=True)
class ResolvedMesh:
    """A validated mesh entry: unique `name` (and file-name `slug`), its spec, resolved `path` and boundary."""

    name: str
    slug: str
    spec: MeshSpec
    path: Path | None
    boundary: BoundarySpec
    mesh: Any = None  # the HexMesh read from `path` (file meshes only)

    @property
    def paper_case(self) -> str | None:
        """The paper case name when this mesh is one of `jaxci.mesh.generate.PAPER_CASES`, else None."""
        return self.spec.generate.case if self.spec.generate is not None else None

    def build(self, seed: int):
        """The input `HexMesh` of the run with `seed` (generated meshes are perturbed by it)."""
        if self.mesh is not None:
            return self.mesh
        from ..mesh.generate import paper_case, perturb_box

        g = self.spec.generate
        s = seed if g.seed is None else g.seed
        if g.case is not None:
            return paper_case(g.case, seed=s)
        return perturb_box(*g.box, amplitude=g.amplitude, seed=s, which=g.which, size=tuple(g.size))


@dataclasses.dataclass(frozen=True)
class ResolvedMethod:
    """A validated method entry: unique `label` (and `slug`), `method` name, `params`, meshes it runs on, and
    the `engine` asked for (`jaxci.interface.engine.engine_request`: with the ``backend`` parameter folded in)."""

    label: str
    slug: str
    method: str
    params: dict
    meshes: tuple[str, ...] | None
    engine: str = "auto"


@dataclasses.dataclass(frozen=True)
class Experiment:
    """A loaded, fully validated config: `config` (the pydantic model), `path`, resolved meshes/methods, seeds."""

    config: ExperimentConfig
    path: Path
    meshes: tuple[ResolvedMesh, ...]
    methods: tuple[ResolvedMethod, ...]
    seeds: tuple[int, ...]

    def runs(self) -> list[tuple[ResolvedMesh, int, ResolvedMethod]]:
        """Every (mesh, seed, method) in run order: mesh-major, then seed (one mesh build per seed), method."""
        out = []
        for m in self.meshes:
            for s in self.seeds:
                out.extend((m, s, meth) for meth in self.methods if meth.meshes is None or m.name in meth.meshes)
        return out


def slugify(text: str) -> str:
    """A file-name-safe form of a label: lower case, runs of other characters as ``-``."""
    return re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-") or "x"


def _validate_params(method: str, params: dict, fail: Callable[[tuple, str], ConfigError]) -> None:
    from ..interface.methods import method_param_class  # the one method -> parameter class table (imported on use)

    cls = method_param_class(method)
    if cls is None:
        return
    names = [f.name for f in dataclasses.fields(cls)]
    for key in params:
        if key not in names:
            raise fail((key,), f"unknown parameter of method {method!r}; valid: {', '.join(names)}")

    build = getattr(cls, "for_method", None)  # per-method defaults (CI: "ci-global" has its own)
    build = cls if build is None else functools.partial(build, method)

    def attempt(kw):
        try:
            build(**kw)
        except (JaxciError, ValueError, TypeError) as e:
            return str(e)
        return None

    msg = attempt(params)
    if msg is None:
        return
    for key, value in params.items():  # name the parameter at fault when it fails on its own
        one = attempt({key: value})
        if one is not None:
            raise fail((key,), one)
    raise fail((), msg)


def load_config(path: str | os.PathLike) -> Experiment:
    """Read and validate an experiment config (YAML), and read its mesh files.

    **Arguments:**

    - `path`: the YAML file; relative mesh paths in it are resolved against its folder.

    **Returns:** an `Experiment`. Raises `ConfigError` (one line: ``file:line: key.path: what is wrong``) for a
    missing or malformed file, unknown keys, wrong types or values, unknown methods or method parameters,
    missing or unreadable mesh files.
    """
    from ..interface.engine import HOST_METHODS, engine_request
    from ..interface.smooth import METHODS
    from ..mesh.generate import PAPER_CASES
    from ..runtime.memory import check_fits, ci_trials, smooth_bytes

    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such config file") from None
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(f"{path}: cannot read the config ({e})") from None
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
        data = yaml.safe_load(text)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f"{path}:{mark.line + 1}" if mark else str(path)
        problem = getattr(e, "problem", None) or str(e).splitlines()[0]
        raise ConfigError(f"{where}: invalid YAML: {problem}") from None
    loc8 = Locator(path, root)
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: the config must be a YAML mapping of keys (mesh, methods, ...), "
                          f"got {type(data).__name__}")
    check_duplicates(root, loc8)
    try:
        cfg = ExperimentConfig.model_validate(data)
    except ValidationError as e:
        errs = e.errors()
        loc, msg = pydantic_message(errs[0], ExperimentConfig)
        more = f" (and {len(errs) - 1} more problems)" if len(errs) > 1 else ""
        raise loc8.error(loc, msg + more) from None

    meshes = []
    names: dict[str, int] = {}
    for i, spec in enumerate(cfg.mesh):
        mpath = None
        if spec.file is not None:
            mpath = Path(spec.file).expanduser()
            if not mpath.is_absolute():
                mpath = (path.parent / mpath).resolve()
            if not mpath.is_file():
                raise loc8.error(("mesh", i, "file"), f"no such mesh file: {mpath}")
        name = spec.name or (mpath.stem if mpath else _generated_name(spec.generate))
        if name in names:
            raise loc8.error(("mesh", i), f"mesh name {name!r} is used twice (entries {names[name]} and {i}); "
                             f"give each a distinct 'name'")
        names[name] = i
        meshes.append((i, name, spec, mpath, spec.boundary or cfg.boundary))
    slugs = _unique_slugs([m[1] for m in meshes], lambda j: loc8.error(("mesh", meshes[j][0]), "mesh names "
                          "must differ in more than punctuation and case (they name files)"))

    resolved_meshes = []
    for (i, name, spec, mpath, bnd), slug in zip(meshes, slugs, strict=True):
        blk = ("mesh", i, "boundary") if spec.boundary else ("boundary",)
        mesh = None
        if mpath is not None:
            from ..io import read_mesh

            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                try:
                    mesh = read_mesh(mpath)
                except JaxciError as e:
                    raise loc8.error(("mesh", i, "file"), str(e)) from None
            n_nodes = mesh.n_nodes
            n_hexes = mesh.n_hexes + sum(len(b.data) for b in mesh.cells if b.type in EXTRA_TYPES)
            for j, s in enumerate(bnd.fixed_sets):
                if s not in mesh.point_sets:
                    known = ", ".join(mesh.point_sets) or "none"
                    raise loc8.error((*blk, "fixed_sets", j), f"mesh {name!r} has no node set {s!r} (sets: {known})")
        else:
            g = spec.generate
            dims = g.box if g.case is None else [PAPER_CASES[g.case].n] * 3  # elements per axis
            n_nodes, n_hexes = math.prod(n + 1 for n in dims), math.prod(dims)
            if bnd.fixed_sets:
                raise loc8.error((*blk, "fixed_sets"), f"generated mesh {name!r} has no node sets")
        trials = max([ci_trials(m.method, m.params) for m in cfg.methods if m.meshes is None or name in m.meshes],
                     default=16)
        check_fits(smooth_bytes(n_hexes, cfg.dtype, trials), f"mesh {name!r}: smoothing {n_hexes:_} elements in "
                   f"{cfg.dtype}", error=lambda msg, i=i: loc8.error(("mesh", i), msg))
        for j, n in enumerate(bnd.fixed_nodes):
            if not 0 <= n < n_nodes:
                raise loc8.error((*blk, "fixed_nodes", j), f"node index {n} out of range [0, {n_nodes}) of {name!r}")
        resolved_meshes.append(ResolvedMesh(name, slug, spec, mpath, bnd, mesh))

    methods = []
    labels: dict[str, int] = {}
    for i, m in enumerate(cfg.methods):
        if m.method not in METHODS:
            raise loc8.error(("methods", i, "method"), f"unknown method {m.method!r}; choose one of "
                             f"{', '.join(METHODS)}")
        label = m.name or m.method
        if label in labels:
            raise loc8.error(("methods", i), f"method label {label!r} is used twice (entries {labels[label]} and "
                             f"{i}); give each a distinct 'name'")
        labels[label] = i
        _validate_params(m.method, m.params, lambda k, msg, i=i: loc8.error(("methods", i, "params", *k), msg))
        try:
            engine, _ = engine_request(m.engine, m.params)
        except ConfigError as e:
            raise loc8.error(("methods", i, "engine"), str(e)) from None
        if engine == "host" and m.method not in (*HOST_METHODS, "auto"):
            raise loc8.error(("methods", i, "engine"), f"engine 'host' cannot run method {m.method!r} (host: "
                             f"{', '.join(HOST_METHODS)}); use engine 'jax' or 'auto'")
        if engine == "host" and cfg.device == "gpu":
            raise loc8.error(("methods", i, "engine"), "engine 'host' runs on the CPU; device: gpu needs engine "
                             "'jax' or 'auto'")
        for j, mn in enumerate(m.meshes or ()):
            if mn not in names:
                raise loc8.error(("methods", i, "meshes", j), f"no mesh named {mn!r}; meshes: {', '.join(names)}")
        methods.append((label, m))
    mslugs = _unique_slugs([lab for lab, _ in methods], lambda j: loc8.error(
        ("methods", j), "method labels must differ in more than punctuation and case (they name files)"))
    resolved_methods = tuple(
        ResolvedMethod(lab, sl, m.method, dict(m.params), tuple(m.meshes) if m.meshes is not None else None,
                       m.engine)
        for (lab, m), sl in zip(methods, mslugs, strict=True)
    )

    t1 = cfg.report.table1
    if t1.mesh is not None and t1.mesh not in names:
        raise loc8.error(("report", "table1", "mesh"), f"no mesh named {t1.mesh!r}; meshes: {', '.join(names)}")
    for key in ("stage1", "stage2"):
        v = getattr(t1, key)
        if v is not None and v not in labels:
            raise loc8.error(("report", "table1", key), f"no method named {v!r}; methods: {', '.join(labels)}")

    seeds = tuple(cfg.seeds) if cfg.seeds is not None else tuple(range(cfg.runs or 1))
    return Experiment(cfg, path, tuple(resolved_meshes), resolved_methods, seeds)


def _generated_name(g: GenerateSpec) -> str:
    return g.case if g.case is not None else "box{}x{}x{}".format(*g.box)


def _unique_slugs(names: list[str], fail) -> list[str]:
    slugs = [slugify(n) for n in names]
    for j, s in enumerate(slugs):
        if s in slugs[:j]:
            raise fail(j)
    return slugs
