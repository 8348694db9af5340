"""Checking method hyperparameters where they enter: types, ranges and upper bounds, one `ConfigError` each.

The parameter dataclasses (`jaxci.optim.ci.CIParams`, `jaxci.optim.gradient.GradientParams`,
`jaxci.optim.laplace.LaplaceParams`, `jaxci.optim.untangle.UntangleParams`) call these in ``__post_init__``; the
values come from Python, YAML (`jaxci.experiments.config`) or the command line (``--param KEY=VALUE``, parsed as JSON,
else a string), so anything can arrive: a string, NaN, a bool, an integer of 40 digits. Each check names the parameter,
the valid range and the value given; an integral float (``4.0``) counts as the integer 4. Upper bounds keep a
typo from hanging a run or exhausting memory (loop bounds, history arrays and batch shapes grow with them).

`make_params` builds a dataclass from a dict of keyword parameters, listing the valid names for an unknown one and
naming the method in every message. (The one seed rule of jaxci, `check_seed`, is `jaxci.mesh.generate`'s.)
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from collections.abc import Mapping

from ..errors import ConfigError, UsageError


def _is_int(value) -> bool:
    if isinstance(value, bool):
        return False
    if isinstance(value, numbers.Integral):
        return True
    return isinstance(value, numbers.Real) and math.isfinite(float(value)) and float(value) == int(value)


def integer(label: str, name: str, value, lo: int, hi: int) -> int:
    """`value` as an int in ``[lo, hi]``, else `ConfigError` ("{label} parameter {name} must be ...")."""
    if not _is_int(value) or not lo <= int(value) <= hi:
        raise ConfigError(f"{label} parameter {name} must be an integer in [{lo}, {hi:_}], got {value!r}")
    return int(value)


def real(label: str, name: str, value, lo: float, hi: float = math.inf, *, lo_open: bool = False,
         hi_open: bool = False) -> float:
    """`value` as a finite float in the interval ``lo..hi`` (open at an end when `lo_open` / `hi_open`)."""
    left, right = "(" if lo_open else "[", ")" if hi_open or math.isinf(hi) else "]"
    ok = isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(float(value))
    if ok:
        v = float(value)
        ok = (v > lo if lo_open else v >= lo) and (v < hi if hi_open else v <= hi)
    if not ok:
        raise ConfigError(f"{label} parameter {name} must be a finite number in {left}{lo:g}, {hi:g}{right}, "
                          f"got {value!r}")
    return float(value)


def boolean(label: str, name: str, value) -> bool:
    """`value` if it is a bool (True / False; not 0, 1 or a string)."""
    if not isinstance(value, bool):
        raise ConfigError(f"{label} parameter {name} must be true or false, got {value!r}")
    return value


def choice(label: str, name: str, value, choices) -> str:
    """`value` if it is one of `choices` (strings)."""
    if not isinstance(value, str) or value not in choices:
        raise ConfigError(f"{label} parameter {name} must be one of {', '.join(map(repr, choices))}, got {value!r}")
    return value


def normalise(obj, **values) -> None:
    """Store checked values on a frozen dataclass instance (an integral float becomes an int, ...)."""
    for k, v in values.items():
        object.__setattr__(obj, k, v)


def make_params(cls, params: Mapping, method: str, *, prefix: str = "", what: str | None = None):
    """An instance of the parameter dataclass `cls` from keyword `params` of `method`.

    **Arguments:** `cls` the dataclass; `params` a mapping of parameter names (each with `prefix` in front, e.g.
    ``"untangle_"``) to values; `method` the method's name, for messages (`what`: instead of ``method 'name'``).

    **Returns:** the instance. Raises `ConfigError` naming the method for an unknown parameter (with the valid
    names) or a bad value.
    """
    what = f"method {method!r}" if what is None else what
    if not isinstance(params, Mapping):
        raise UsageError(f"parameters of {what} must be a mapping of names to values, got {type(params).__name__}")
    names = [f.name for f in dataclasses.fields(cls)]
    kwargs = {}
    for key, value in params.items():
        name = key[len(prefix):] if isinstance(key, str) and key.startswith(prefix) else None
        if name not in names:
            raise ConfigError(f"unknown parameter {key!r} of {what}; valid: "
                              f"{', '.join(prefix + n for n in names)}")
        kwargs[name] = value
    try:
        return cls(**kwargs)
    except ConfigError as e:
        raise ConfigError(f"{what}: {e}") from None


#: Where a method runs (the `backend` parameter of L-BFGS, CI and the Laplacians): ``"auto"`` (on the host, numpy
#: and C, up to a size; compiled above it), ``"jax"`` (compiled), ``"numpy"`` (on the host).
BACKENDS = ("auto", "jax", "numpy")

#: Consecutive rejected trials after which a solver whose steps are capped (`max_move`) stops (`jaxci.optim.lbfgs`,
#: `jaxci.optim._solve.solve_loop`, `jaxci.optim.host.lbfgs`): the trial is then below 2^-20 of `max_move`; in float32
#: that is F's rounding noise at the optimum (measured: 28 rejected trials ended every L-BFGS run at 30^3 after it had
#: converged, each a full objective and gradient evaluation). Uncapped solvers (and LM, Gauss-Newton) get
#: `MAX_REJECTED_UNCAPPED`: their first raw-gradient trial can be 2^35 times too long.
MAX_REJECTED = 20
MAX_REJECTED_UNCAPPED = 64
#: The untangling rounds' L-BFGS memory (pairs), on both engines (`jaxci.optim.host.untangle_rounds_np`,
#: `jaxci.optim._untangle_loop.untangle_rounds`).
UNTANGLE_HISTORY = 10
