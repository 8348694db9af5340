"""Structured box meshes and the seeded perturbation protocol used for the paper's test cases.

The perturbation protocol (`perturb_box`): with grid spacing h = (hx, hy, hz) and amplitude a,

- interior nodes move uniformly in [-a h_d, +a h_d] along each axis d;
- surface nodes move the same way along the two axes of their face only (they stay on the face);
- edge nodes move along their edge only;
- the 8 box corners stay fixed.

With ``which="interior"`` only interior nodes move (the boundary is exactly the grid). With
``redraw_inverted=True`` (default) the nodes of any element that would get a corner with det <= 0 are drawn
again (up to `max_redraws` rounds), so the result has no inverted element. Same arguments and seed, same mesh.
"""

from __future__ import annotations

import dataclasses
import math
import numbers

import numpy as np

from ..cells import corner_determinants
from ..errors import ConfigError, MeshError
from ..runtime.memory import check_fits, generate_bytes
from . import HexMesh, hex_mesh

#: Largest seed: seeds are integers in [0, MAX_SEED]. A `jax.random` key from an integer keeps 32 bits of it
#: (2**32 and 0 gave the same key), so larger seeds are refused rather than silently aliased.
MAX_SEED = 2**32 - 1


def check_seed(seed, what: str = "seed") -> int:
    """`seed` as an int in ``[0, MAX_SEED]`` (`ConfigError` otherwise: a float, a string, None, a bool, a negative
    or a larger integer). Every accepted seed gives its own `jax.random` key and numpy generator."""
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral):
        raise ConfigError(f"{what} must be an integer in [0, 2**32 - 1], got {seed!r}")
    if not 0 <= int(seed) <= MAX_SEED:
        raise ConfigError(f"{what} must be an integer in [0, 2**32 - 1] (= {MAX_SEED}), got {seed!r}")
    return int(seed)


def grid_hexes(ni: int, nj: int, nk: int, periodic_j: bool = False) -> np.ndarray:
    """Hexahedra of a structured ``ni x nj x nk`` grid whose node (i, j, k) has index
    ``i + (ni+1) * (j + nJ * k)`` with ``nJ = nj`` when `periodic_j` (j wraps around) else ``nj + 1``.
    Shape ``(ni nj nk, 8)``, int64; right-handed when the grid axes i, j, k are."""
    n_j = nj if periodic_j else nj + 1

    def nid(i, j, k):
        return i + (ni + 1) * ((j % n_j) + n_j * k)

    k, j, i = np.meshgrid(np.arange(nk), np.arange(nj), np.arange(ni), indexing="ij")
    i, j, k = i.ravel(), j.ravel(), k.ravel()
    # VTK order: the corners (i, j), (i+1, j), (i+1, j+1), (i, j+1) at k, then the same at k + 1
    return np.stack([nid(i + a, j + b, k + c) for c in (0, 1) for a, b in ((0, 0), (1, 0), (1, 1), (0, 1))],
                    axis=1).astype(np.int64)


def box(
    nx: int,
    ny: int | None = None,
    nz: int | None = None,
    *,
    size: tuple[float, float, float] = (1.0, 1.0, 1.0),
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> HexMesh:
    """A structured box of ``nx * ny * nz`` right-handed hexahedra.

    Node (i, j, k) has index ``i + (nx+1) * (j + (ny+1) * k)`` and lies at ``origin + (i hx, j hy, k hz)``.

    **Arguments:** `nx`, `ny`, `nz` element counts per axis (`ny`, `nz` default to `nx`); `size` the box edge
    lengths; `origin` its minimum corner.

    **Returns:** a `HexMesh` with ``(nx+1)(ny+1)(nz+1)`` nodes and ``nx ny nz`` hexahedra.
    """
    nx, ny, nz = _counts("box", nx, ny, nz)
    size = _triple("box", "size", size, positive=True)
    origin = _triple("box", "origin", origin, positive=False)
    check_fits(generate_bytes(nx * ny * nz), f"box: a box of {nx} x {ny} x {nz} = {nx * ny * nz:_} hexahedra")
    xs, ys, zs = (origin[d] + np.linspace(0.0, size[d], m + 1) for d, m in enumerate((nx, ny, nz)))
    z, y, x = np.meshgrid(zs, ys, xs, indexing="ij")
    points = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    return hex_mesh(points, grid_hexes(nx, ny, nz))


def _counts(fn: str, nx, ny, nz) -> tuple[int, int, int]:
    """Element counts per axis as ints >= 1 (`ny`, `nz` default to `nx`); `MeshError` naming the bad one."""
    ny = nx if ny is None else ny
    nz = nx if nz is None else nz
    for name, v in (("nx", nx), ("ny", ny), ("nz", nz)):
        if isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(v) or int(v) != v or v < 1:
            raise MeshError(f"{fn}: {name} must be a positive integer, got {v!r}")
    return int(nx), int(ny), int(nz)


def _triple(fn: str, name: str, v, positive: bool) -> tuple[float, float, float]:
    """Three finite numbers (> 0 if `positive`) as floats; `MeshError` otherwise."""
    try:
        t = tuple(v)
    except TypeError:
        t = ()
    ok = len(t) == 3 and all(isinstance(a, numbers.Real) and not isinstance(a, bool) and math.isfinite(a)
                             and (a > 0 or not positive) for a in t)
    if not ok:
        what = "positive finite edge lengths" if positive else "finite coordinates"
        raise MeshError(f"{fn}: {name} must be three {what}, got {v!r}")
    return tuple(float(a) for a in t)


def box_free_axes(nx: int, ny: int, nz: int, which: str = "sliding") -> np.ndarray:
    """Per node of `box(nx, ny, nz)`, which axes it may move along: a bool array of shape ``(n_nodes, 3)``.

    ``which="sliding"``: interior nodes all three axes, face nodes the two tangent axes, edge nodes the edge axis,
    corners none. ``which="interior"``: interior nodes only.
    """
    k, j, i = np.meshgrid(np.arange(nz + 1), np.arange(ny + 1), np.arange(nx + 1), indexing="ij")
    inner = np.stack(
        [(i > 0) & (i < nx), (j > 0) & (j < ny), (k > 0) & (k < nz)], axis=-1
    ).reshape(-1, 3)
    if which == "sliding":
        return inner
    if which == "interior":
        return inner & inner.all(axis=1, keepdims=True)
    raise MeshError(f"perturbation 'which' must be 'sliding' or 'interior', got {which!r}")


def perturb_box(
    nx: int,
    ny: int | None = None,
    nz: int | None = None,
    *,
    amplitude: float = 0.3,
    seed: int = 0,
    which: str = "sliding",
    size: tuple[float, float, float] = (1.0, 1.0, 1.0),
    redraw_inverted: bool = True,
    max_redraws: int = 1000,
) -> HexMesh:
    """A box mesh with its nodes perturbed by the seeded protocol of this module's docstring.

    **Arguments:** `nx, ny, nz` and `size` as for `box`; `amplitude` a (fraction of the spacing, >= 0);
    `seed` an integer seed of numpy's default generator; `which` ``"sliding"`` or ``"interior"``;
    `redraw_inverted` redraw nodes of elements that would invert.

    **Returns:** a `HexMesh`. Raises `MeshError` if no valid draw was found in `max_redraws` rounds.
    """
    nx, ny, nz = _counts("perturb_box", nx, ny, nz)
    if isinstance(amplitude, bool) or not isinstance(amplitude, numbers.Real) or not 0 <= amplitude <= 10:
        raise MeshError(f"perturb_box: amplitude must be a number in [0, 10] (a fraction of the grid spacing), "
                        f"got {amplitude!r}")
    seed = check_seed(seed, "perturb_box: seed")
    if not isinstance(which, str) or which not in ("sliding", "interior"):
        raise MeshError(f"perturb_box: which must be 'sliding' or 'interior', got {which!r}")
    if not isinstance(redraw_inverted, bool):
        raise MeshError(f"perturb_box: redraw_inverted must be True or False, got {redraw_inverted!r}")
    if isinstance(max_redraws, bool) or not isinstance(max_redraws, numbers.Integral) or \
            not 1 <= max_redraws <= 1_000_000:
        raise MeshError(f"perturb_box: max_redraws must be an integer in [1, 1_000_000], got {max_redraws!r}")
    size = _triple("perturb_box", "size", size, positive=True)
    mesh = box(nx, ny, nz, size=size)
    h = np.array([size[0] / nx, size[1] / ny, size[2] / nz])
    free = box_free_axes(nx, ny, nz, which)
    rng = np.random.default_rng(seed)
    base = mesh.points

    def draw(n):
        return rng.uniform(-1.0, 1.0, size=(n, 3)) * amplitude * h

    points = base + draw(len(base)) * free
    hexes = mesh.hexes
    if redraw_inverted:
        for _ in range(max_redraws):
            bad = (corner_determinants(points, hexes) <= 0).any(axis=1)
            if not bad.any():
                break
            nodes = np.unique(hexes[bad])
            points[nodes] = base[nodes] + draw(len(nodes)) * free[nodes]
        else:
            raise MeshError(
                f"perturb_box: no perturbation without inverted elements after {max_redraws} redraws "
                f"(amplitude {amplitude} is too large)"
            )
    # below half a spacing each node stays inside its own box around its grid point: no two can coincide
    return mesh.with_points(points, coincident=np.zeros((0, 2), np.int64) if amplitude < 0.5 else None)


@dataclasses.dataclass(frozen=True)
class PaperCase:
    """One of the paper's cubes: `n` elements per axis and the perturbation that gives its 'before' quality."""

    name: str
    n: int
    amplitude: float
    which: str = "sliding"

    def mesh(self, seed: int = 0) -> HexMesh:
        """The perturbed cube for `seed` (an integer in [0, 2**32 - 1])."""
        return perturb_box(self.n, amplitude=self.amplitude, seed=seed, which=self.which)


#: The paper's three cases (27, 64 and 729 hexahedra on the unit cube), by name, with the sliding protocol of
#: `perturb_box` (interior, face and edge nodes all perturbed, corners fixed, inverting draws redrawn). The paper
#: gives no protocol; these amplitudes give 'before' max kappa/3 of the order of its Table 2 (510, 26, 12):
#: over seeds 0-29 the median (min, max) is 21.6 (4.6, 2310) for cube27 at a = 0.5, 18.4 (4.6, 343) for
#: cube64 at a = 0.4 and 8.8 (2.7, 134) for cube729 at a = 0.25 (heavy tails: one nearly flat corner is enough).
PAPER_CASES: dict[str, PaperCase] = {
    "cube27": PaperCase("cube27", 3, 0.5),
    "cube64": PaperCase("cube64", 4, 0.4),
    "cube729": PaperCase("cube729", 9, 0.25),
}


def paper_case(name: str, seed: int = 0) -> HexMesh:
    """The perturbed cube of the paper's case `name` (one of `PAPER_CASES`) for `seed`."""
    try:
        case = PAPER_CASES[name]
    except KeyError:
        raise MeshError(f"unknown paper case {name!r}; known: {', '.join(PAPER_CASES)}") from None
    return case.mesh(seed)
