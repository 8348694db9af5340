"""Shared test fixtures: where ../shared is, the real meshes and their published figures."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
MESQUITE = SHARED / "data" / "mesquite"
EXODUS = SHARED / "data" / "exodus"
PEERS = SHARED / "peers"

#: The files a test marked ``shared`` may read: one per folder of ../shared it uses.
SHARED_FILES = (MESQUITE / "pave3.e.vtk", EXODUS / "cube.g", PEERS / "cube9_pert.vtk")


def cpu_env(devices: int | None = None) -> dict[str, str]:
    """``os.environ`` for a subprocess on the CPU: the suite's own XLA flags (conftest: LLVM's cheaper pipeline and
    XLA's older code generation; the 4-device tests 20-24 s with them against 40-48 s) without any forced device
    count, plus ``--xla_force_host_platform_device_count=devices`` where `devices` is given (read when JAX starts
    there)."""
    flags = [f for f in os.environ.get("XLA_FLAGS", "").split() if not f.startswith("--xla_force_host_platform")]
    if devices is not None:
        flags.append(f"--xla_force_host_platform_device_count={devices}")
    return dict(os.environ, XLA_FLAGS=" ".join(flags), JAX_PLATFORMS="cpu")


def shared_missing() -> list[Path]:
    """The files of `SHARED_FILES` that are not there (empty when ../shared is complete)."""
    return [p for p in SHARED_FILES if not p.is_file()]


#: Why a test marked ``shared`` is skipped where ../shared is missing: what is missing and how to get it.
SHARED_REASON = (
    "needs the real meshes of ../shared (data/mesquite: Mesquite's meshFiles/3D/vtk/hexes from github.com/trilinos/"
    "mesquite; data/exodus: SEACAS test files from github.com/sandialabs/seacas; peers: Mesquite's cubes), "
    f"not found beside the repository at {SHARED}; put the project's shared/ folder there to run them"
)

#: ../shared/data/mesquite/README.md: file -> (hexes, nodes, inverted corners, inverted elements, max k/3, F,
#: min corner scaled Jacobian); None where the README gives '-' or 'inf'.
MESQUITE_FIGURES = {
    "single_hex.vtk": (1, 8, 0, 0, None, None, None),
    "hexes_4by2by2.vtk": (16, 45, 0, 0, 1.203, 0.04164, 0.894),
    "large_box_hex_1000.vtk": (1000, 1331, 0, 0, 1.101, 0.03362, 0.882),
    "1000hex-block-internal-bias.vtk": (1000, 1331, 0, 0, 8.448, 5.868, 0.126),
    "hex_5_tangled.vtk": (125, 216, 48, 36, None, None, -0.865),
    "pave3.e.vtk": (1791, 2385, 258, 106, None, None, -0.854),
}


#: A small experiment config: local CI (3 sweeps) on the 27-hex cube, seeds 0 and 1.
CUBE27_EXPERIMENT = """\
mesh:
  generate: {case: cube27}
methods:
  - name: CI local
    method: ci
    params: {max_sweeps: 3}
seeds: [0, 1]
"""


#: `CUBE27_EXPERIMENT` without its figures: a quick `jaxci run`.
QUICK_EXPERIMENT = CUBE27_EXPERIMENT + "figures: false\n"


def complete_results(tmp_path_factory) -> Path:
    """A complete results folder of `QUICK_EXPERIMENT` (`jaxci run`), to copy as a test's earlier results."""
    from jaxci.cli import main

    folder = tmp_path_factory.mktemp("earlier")
    (folder / "exp.yaml").write_text(QUICK_EXPERIMENT)
    assert main(["run", str(folder / "exp.yaml"), "--out", str(folder / "prev"), "--quiet"]) == 0
    return folder / "prev"


def box_or_mesquite(name: str, seed: int):
    """``box<k>``: `perturb_box(k)` (amplitude 0.3, `seed`); else the Mesquite mesh `name` of ../shared/data/mesquite
    (the test skipped with `SHARED_REASON` where it is absent)."""
    import pytest

    from jaxci.io import read_mesh
    from jaxci.mesh.generate import perturb_box

    if name.startswith("box"):
        return perturb_box(int(name[3:]), amplitude=0.3, seed=seed)
    path = MESQUITE / name
    if not path.exists():
        pytest.skip(SHARED_REASON)
    return read_mesh(path)


def unit_cube() -> np.ndarray:
    """The 8 nodes of the unit cube in VTK order, shape (8, 3)."""
    return np.array(
        [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], dtype=float
    )


def random_valid_hexes(rng: np.random.Generator, n: int, amplitude: float = 0.25) -> np.ndarray:
    """`n` random valid hexahedra (unit cube corners moved by up to `amplitude`, kept if all det > 0), (n, 8, 3)."""
    from jaxci.cells import corner_determinants

    out = []
    while len(out) < n:
        x = unit_cube()[None] + rng.uniform(-amplitude, amplitude, size=(4 * n, 8, 3))
        conn = np.arange(8)[None]
        for h in x:
            if (corner_determinants(h, conn) > 0).all():
                out.append(h)
    return np.array(out[:n])


def read_vtk_hexes(path) -> tuple[np.ndarray, np.ndarray]:
    """Points and hexahedra of a legacy VTK file, read by meshio directly (independent of jaxci.io)."""
    import meshio

    m = meshio.vtk.read(str(path))
    return np.asarray(m.points, dtype=float), np.asarray(m.cells_dict["hexahedron"])


def interrupted_on_call(real, n: int = 2):
    """`real` wrapped to raise KeyboardInterrupt (as Ctrl-C would) on its `n`-th call instead of running."""
    calls = []

    def wrapped(*args, **kwargs):
        calls.append(1)
        if len(calls) == n:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    return wrapped


def fail_seed_method(monkeypatch, seed: int, error: Exception) -> None:
    """Make the method run of seed `seed` raise `error` (`jaxci.interface.methods.run_method`, where
    `MethodRun.run` looks it up); every other seed runs as it would."""
    from jaxci.interface import methods

    run_method = methods.run_method

    def failing(problem, method, s, params):
        if s == seed:
            raise error
        return run_method(problem, method, s, params)

    monkeypatch.setattr(methods, "run_method", failing)


def spiked_sweep():
    """A 4^3 box perturbed by 0.1 h and a sweep displacement D along which F falls fastest at the factor 4, where
    one node moved too far makes the worst corner worse (max kappa/3 1.196 against 1.084); at the factor 2 both F and
    the max are lower (0.0201, 1.043)."""
    from jaxci.mesh.generate import perturb_box

    grid = perturb_box(4, amplitude=0.0)
    mesh = perturb_box(4, amplitude=0.1, seed=2)
    error = np.asarray(mesh.points) - np.asarray(grid.points)
    spike = np.zeros_like(error)
    spike[31] = [0.1, 0.1, 0.05]  # an interior node, 0.4 h at the factor 8
    return mesh, (spike - error) / 8


@contextlib.contextmanager
def no_implicit_transfers():
    """Within the body, an implicit transfer between host and device raises: JAX's transfer guard
    (``jax.transfer_guard("disallow")``: numpy arrays or Python scalars into compiled code, eager jax.numpy on
    host values), and, for the copies of device arrays to numpy that the guard lets through on a CPU (the array's
    buffer protocol), `numpy.asarray` / `array` / `asanyarray` / `ascontiguousarray` of a device array and the
    conversions that go through ``jax.Array._value`` (``float``, ``int``, ``bool``, ``tolist``, ``item``),
    outside `jaxci.runtime.transfer.to_host`. A numpy function applied to a device array directly (``np.max(x)``)
    converts it inside numpy's C code and is not caught here."""
    import jax

    from jaxci.runtime import transfer

    array_type = type(jax.device_put(0.0))
    value = array_type.__dict__["_value"]

    def refuse(what):
        raise AssertionError(f"implicit device-to-host transfer ({what}) outside jaxci.runtime.transfer.to_host")

    def checked_value(self):
        if not transfer.explicit():
            refuse("jax.Array._value")
        return value.fget(self)

    originals = {name: getattr(np, name) for name in ("asarray", "array", "asanyarray", "ascontiguousarray")}

    def wrap(name, fn):
        def checked(a, *args, **kwargs):
            if isinstance(a, jax.Array) and not transfer.explicit():
                refuse(f"numpy.{name}")
            return fn(a, *args, **kwargs)
        return checked

    array_type._value = property(checked_value)
    for name, fn in originals.items():
        setattr(np, name, wrap(name, fn))
    try:
        with jax.transfer_guard("disallow"):
            yield
    finally:
        array_type._value = value
        for name, fn in originals.items():
            setattr(np, name, fn)


def wavy_annulus(n_theta: int = 32, n_r: int = 4, n_z: int = 4, seed: int = 0):
    """An annulus whose nodes are moved along its walls (and inside; none inverted): the boundary stays the two
    cylinders and the end planes, so its nodes slide on curved (faceted) walls."""
    import numpy as np

    from jaxci.mesh.shapes import annulus

    m = annulus(n_theta, n_r, n_z)
    p = np.array(m.points)
    rng = np.random.default_rng(seed)
    r, th, z = np.hypot(p[:, 0], p[:, 1]), np.arctan2(p[:, 1], p[:, 0]), p[:, 2]
    r = np.where((r > 0.5 + 1e-9) & (r < 1 - 1e-9), r + rng.uniform(-0.15, 0.15, len(r)) / n_r, r)
    th = th + rng.uniform(-0.3, 0.3, len(r)) * 2 * np.pi / n_theta
    z = np.where((z > 1e-9) & (z < 1 - 1e-9), z + rng.uniform(-0.3, 0.3, len(z)) / n_z, z)
    return m.with_points(np.stack([r * np.cos(th), r * np.sin(th), z], axis=1))
