"""Corner Jacobians, condition numbers, scaled Jacobians and the paper's objective F, batched in JAX.

Definitions (``shared/reference/metrics.md``, matching VTK/Verdict): at corner i of a hexahedron the matrix A_i
has as columns the three edge vectors from node i to the nodes `jaxci.cells.CORNER_NEIGHBOURS[i]`. With columns
a, b, c:

- det A = a . (b x c)  (> 0 for a valid corner; <= 0 is an inverted or degenerate corner);
- kappa(A) = |A|_F |A^-1|_F = sqrt(|a|^2+|b|^2+|c|^2) sqrt(|b x c|^2+|c x a|^2+|a x b|^2) / det A, >= 3;
  we report kappa/3, in [1, inf), 1 only for a corner with orthogonal columns of equal length;
- corner scaled Jacobian = det A / (|a| |b| |c|), in [-1, 1];
- element condition = max over its 8 corners of kappa/3 (VTK ``HexCondition``), element mean = mean over the
  8 corners (VTK ``HexMedAspectFrobenius``);
- the paper's Eq. 3.1: F = 1/(8N) sum_n sum_i (kappa(A_ni)/3)^2 - 1, 0 only for a mesh of perfect cubes.

An inverted corner (det <= 0) has no meaningful condition number: the per-corner condition is ``inf`` there,
the objective is ``inf`` for any mesh with an inverted corner (a barrier for the optimizers), and the report
counts inverted corners separately and computes its figures over valid corners only.

Fast path: the closed form above with every 3x3 entry as its own array (structure of arrays, one 1-D gather per
component and local node). Reference path: `jnp.linalg.cond` on the stacked matrices (``"frobenius-cond"``:
``cond(A, 'fro') / 3``, the same number; ``"2-norm"``: the SVD condition number, a different metric).

Every public kernel takes `points` of shape ``(n, 3)`` or ``(C, n, 3)`` (C candidates of a cohort) and `hexes`
of shape ``(N, 8)``, and returns arrays with the same leading candidate axis. Candidates are mapped with
`jax.lax.map` around the mesh gather (a `vmap` of the gather is 10-40x slower on CPU, see ecosystem.md).
"""

from __future__ import annotations

import functools

import numpy as np

from ..cells import CORNER_NEIGHBOURS, corner_invariants, edge_lengths2, pmean_weights, scaled_ratio
from ..runtime._lazy import compute_platform, is_jax_array, jax, jit, jnp
from .incidence import accumulate, scatter_add

#: Names of the per-corner condition metrics `corner_condition` accepts.
METRICS = ("frobenius", "frobenius-cond", "2-norm")

_NB = tuple(tuple(int(v) for v in CORNER_NEIGHBOURS[:, j]) for j in range(3))


# ---------------------------------------------------------------------------------------------- kernels
def gather_corners(points, conn, xp=jnp):
    """Node coordinates per local node, structure of arrays.

    **Arguments:** `points` of shape ``(n, 3)``; `conn` the TRANSPOSED connectivity, shape ``(k, N)`` (``(8, N)``
    for hexahedra: `hexes.T`, one contiguous row of node indices per local node, 2x faster to gather than
    ``(N, 8)``); `xp` the array module (`jax.numpy`, default, or `numpy`).

    **Returns:** ``(X, Y, Z)``, each of shape ``(k, N)``: component of local node a of element e at ``[a, e]``.
    """
    pt = points.T
    return tuple(xp.stack([pt[d][conn[a]] for a in range(conn.shape[0])]) for d in range(3))


def transposed(hexes):
    """``(N, 8)`` hexahedra -> the ``(8, N)`` contiguous layout the kernels take (int32 unless x64 is on)."""
    if is_jax_array(hexes):
        return hexes.T
    # converted on the host and device_put: jnp.asarray of a numpy array compiles a small program per shape
    a = np.asarray(hexes)
    return jax.device_put(np.ascontiguousarray(a.T, dtype=jax.dtypes.canonicalize_dtype(a.dtype)))


def corner_columns(X, Y, Z):
    """The three columns of every corner matrix from `gather_corners` output.

    **Returns:** a tuple of 9 arrays ``(ax, ay, az, bx, by, bz, cx, cy, cz)``, each of shape ``(8, N)``
    (corner i of element e at ``[i, e]``).
    """
    out = []
    for nb in _NB:
        idx = np.array(nb)
        out.extend([X[idx] - X, Y[idx] - Y, Z[idx] - Z])
    return tuple(out)


def condition_from_invariants(det, fro2, adj2):
    """kappa/3 from `corner_invariants` output; ``inf`` where det <= 0."""
    valid = det > 0
    safe = jnp.where(valid, det, 1.0)
    return jnp.where(valid, jnp.sqrt(fro2 * adj2) / (3.0 * safe), jnp.inf)


def squared_condition_from_invariants(det, fro2, adj2, xp=jnp):
    """(kappa/3)^2 (the per-corner term of Eq. 3.1 plus 1) from `corner_invariants`; ``inf`` where det <= 0. `xp`:
    the array module (`jax.numpy`, default, or `numpy`)."""
    valid = det > 0
    safe = xp.where(valid, det, 1.0)
    return xp.where(valid, fro2 * adj2 / (9.0 * safe * safe), xp.inf)


def _batched(fn):
    """Make a kernel of ``(points (n,3), conn (8,N))`` accept ``(C, n, 3)`` points too (lax.map over candidates)."""

    @functools.wraps(fn)
    def wrapper(points, conn, *args):
        if points.ndim == 3:
            return jax.lax.map(lambda p: fn(p, conn, *args), points)
        if points.ndim != 2 or points.shape[-1] != 3:
            raise ValueError(f"points must have shape (n, 3) or (C, n, 3), got {points.shape}")
        return fn(points, conn, *args)

    return wrapper


@jit
@_batched
def corner_kernel(points, conn):
    """det A_i, |A_i|_F^2, |adj A_i|_F^2 and |a|^2|b|^2|c|^2 per corner (jitted; `conn` the transposed ``(8, N)``
    connectivity), each of shape ``(..., N, 8)``."""
    cols = corner_columns(*gather_corners(points, conn))
    det, fro2, adj2 = corner_invariants(*cols)
    return det.T, fro2.T, adj2.T, edge_lengths2(*cols).T


def as_points(points, dtype=None):
    """`points` as a JAX array of a floating dtype (`dtype`, else the default float)."""
    arr = jnp.asarray(points, dtype=dtype)
    if not jnp.issubdtype(arr.dtype, jnp.floating):
        arr = arr.astype(jnp.result_type(float))
    return arr


# ---------------------------------------------------------------------------------------------- public API
def corner_matrices(points, hexes):
    """The corner matrices A_i, columns = edge vectors.

    **Arguments:** `points` of shape ``(n, 3)`` or ``(C, n, 3)``; `hexes` of shape ``(N, 8)``.

    **Returns:** shape ``(..., N, 8, 3, 3)``; ``A[..., e, i, :, j]`` is column j of corner i of element e.
    """
    pts = as_points(points)
    hx = jnp.asarray(hexes)
    x = pts[..., hx, :]  # (..., N, 8, 3)
    nb = jnp.asarray(CORNER_NEIGHBOURS)
    cols = x[..., nb, :] - x[..., :, None, :]  # (..., N, 8, 3 columns, 3 components)
    return jnp.swapaxes(cols, -1, -2)


def corner_determinant(points, hexes):
    """det A_i per corner, shape ``(..., N, 8)`` (<= 0: inverted or degenerate corner)."""
    return corner_kernel(as_points(points), transposed(hexes))[0]


def corner_condition(points, hexes, metric: str = "frobenius"):
    """Per-corner condition number, shape ``(..., N, 8)``; ``inf`` at corners with det <= 0.

    **Arguments:**

    - `points`: shape ``(n, 3)`` or ``(C, n, 3)``; `hexes`: shape ``(N, 8)``.
    - `metric`: ``"frobenius"`` (default): kappa/3 in closed form, the fast path, in [1, inf);
      ``"frobenius-cond"``: ``jnp.linalg.cond(A, 'fro') / 3``, the same number by the reference route;
      ``"2-norm"``: ``jnp.linalg.cond(A)``, the SVD (spectral) condition number, another metric in [1, inf).
    """
    pts = as_points(points)
    if metric == "frobenius":
        det, fro2, adj2, _ = corner_kernel(pts, transposed(hexes))
        return condition_from_invariants(det, fro2, adj2)
    if metric not in METRICS:
        raise ValueError(f"unknown condition metric {metric!r}; choose one of {', '.join(METRICS)}")
    return _reference_condition(pts, jnp.asarray(hexes), metric == "2-norm")


@jit(static_argnums=2)
def _reference_condition(points, hexes, two_norm: bool):
    a = corner_matrices(points, hexes)
    det = jnp.linalg.det(a)
    k = jnp.linalg.cond(a) if two_norm else jnp.linalg.cond(a, "fro") / 3.0
    return jnp.where(det > 0, k, jnp.inf)


def corner_scaled_jacobian(points, hexes):
    """det A_i / (|a||b||c|) per corner, shape ``(..., N, 8)``, in [-1, 1] (0 where an edge has length 0)."""
    det, _, _, l2 = corner_kernel(as_points(points), transposed(hexes))
    return scaled_ratio(jnp, det, l2)


#: The hexahedron's three principal axes, each the sum of the edges ``X[j] - X[i]`` of these local node pairs.
_AXES = (((0, 1), (3, 2), (4, 5), (7, 6)), ((0, 3), (1, 2), (4, 7), (5, 6)), ((0, 4), (1, 5), (2, 6), (3, 7)))


def centre_scaled_jacobian(X, Y, Z, xp=jnp):
    """The scaled Jacobian at the centre (of the principal axes) of every hexahedron from `gather_corners`
    output, ``(N,)``: Verdict's term of ``hex_scaled_jacobian`` beside the corners'."""
    cols = tuple(sum(C[j] - C[i] for i, j in pairs) for pairs in _AXES for C in (X, Y, Z))
    return scaled_ratio(xp, corner_invariants(*cols)[0], edge_lengths2(*cols))


@jit
@_batched
def _centre_scaled_jacobian(points, conn):
    return centre_scaled_jacobian(*gather_corners(points, conn))


def element_scaled_jacobian(points, hexes):
    """Verdict's ``hex_scaled_jacobian``: min over the 8 corners and the centre (principal axes), ``(..., N)``."""
    centre = _centre_scaled_jacobian(as_points(points), transposed(hexes))
    return jnp.minimum(corner_scaled_jacobian(points, hexes).min(axis=-1), centre)


def element_condition(points, hexes, metric: str = "frobenius"):
    """Max corner condition per element (VTK ``HexCondition`` for the default metric), ``(..., N)``."""
    return corner_condition(points, hexes, metric).max(axis=-1)


@jit
@_batched
def objective_t(points, conn):
    """`objective` on the transposed connectivity `conn` of shape ``(8, N)`` (jitted; what optimizers call)."""
    det, fro2, adj2 = corner_invariants(*corner_columns(*gather_corners(points, conn)))
    term = squared_condition_from_invariants(det, fro2, adj2)
    return jnp.mean(jax.lax.optimization_barrier(term) - 1.0)  # summands near 0, not near 1: less rounding


def objective(points, hexes):
    """The paper's objective F (Eq. 3.1): mean over all 8N corners of (kappa/3)^2, minus 1.

    **Arguments:** `points` of shape ``(n, 3)`` or ``(C, n, 3)``; `hexes` of shape ``(N, 8)``.

    **Returns:** a scalar, or shape ``(C,)``; >= 0, 0 only for perfect cubes, ``inf`` if any corner has
    det <= 0 (so that no optimizer can accept an inverted mesh as an improvement).
    """
    return objective_t(as_points(points), transposed(hexes))


# ---------------------------------------------------------------------------------------------- gradient of F
def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


#: Per column j, the corner whose column j ends at each local node (static Python ints).
_COLUMN_OWNER = [tuple(int(i) for i in np.argsort(CORNER_NEIGHBOURS[:, j])) for j in range(3)]


def _rows(xp, a, order):
    """``a[order]`` along the first axis by static slices (no index array: its dtype follows jax_enable_x64)."""
    return xp.stack([a[i] for i in order])


def objective_and_grad(points, conn):
    """F (Eq. 3.1) and its gradient with respect to the node coordinates, in closed form.

    (`objective_terms_and_grad` without the max.)

    **Arguments:** `points` of shape ``(n, 3)``; `conn` the transposed connectivity ``(8, N)``.

    **Returns:** ``(F, grad)``: a scalar (``inf`` if any corner has det <= 0) and shape ``(n, 3)``.
    """
    f, _, g = objective_terms_and_grad(points, conn)
    return f, g


#: Elements per block of `objective_terms_and_grad` (`_terms_and_grad_blocks`) on meshes of more than
#: `GRAD_BLOCK_FROM` elements: evaluated block by block, only one block's corner arrays are live (XLA's temporaries
#: of the kernel at 60^3, float32: 176 MB whole, 18 MB in blocks of 16,384). Measured (2-core CPU, shared, float32):
#: the kernel alone at 60^3 is as fast in blocks (220 ms against 245-390 ms whole), but inside the compiled L-BFGS
#: loop (40^3, 60 steps) the steps took 1.4-1.5x longer and the compilation 5 s more; hence blocks only where the
#: whole mesh's temporaries (~1.45 kB per hexahedron) would not fit comfortably.
GRAD_BLOCK = 16_384
GRAD_BLOCK_FROM = 4_000_000

#: `GRAD_BLOCK` on an accelerator: a block of 16,384 elements is far too small a kernel for a GPU (H200, float32,
#: 10^7 hexahedra: 2.8 G corners/s in such blocks against 9.1 G at 10^6 whole); 2^20 elements keep each kernel
#: large and its temporaries near 1.5 GB.
GRAD_BLOCK_ACCELERATOR = 1 << 20


def grad_block(n_elements: int) -> int:
    """The block size `objective_terms_and_grad` uses by default on `n_elements` elements on the platform JAX
    computes on (its default device's): 0 (the whole mesh) up to `GRAD_BLOCK_FROM`, else `GRAD_BLOCK` on a CPU
    and `GRAD_BLOCK_ACCELERATOR` elsewhere."""
    if n_elements <= GRAD_BLOCK_FROM:
        return 0
    return GRAD_BLOCK if compute_platform() == "cpu" else GRAD_BLOCK_ACCELERATOR


def objective_terms_and_grad(points, conn, weight=None, power=None, block: int | None = None, n_corners=None,
                             incidence=None):
    """F (Eq. 3.1), max kappa/3 and the gradient of F with respect to the node coordinates, in closed form.

    With columns a, b, c of a corner matrix, u = b x c, v = c x a, w = a x b, det = a . u,
    |A|^2 = |a|^2 + |b|^2 + |c|^2 and |adj A|^2 = |u|^2 + |v|^2 + |w|^2, the term t = |A|^2 |adj A|^2 / (9 det^2)
    has ``dt/da = t (2 a / |A|^2 + 2 (v x c + b x w) / |adj A|^2 - 2 u / det)`` (and cyclically for b, c); a
    column is the difference of two nodes, so its gradient goes to one node with + and to the corner's node
    with -; the 8 per-element node gradients are summed into the nodes (`incidence`).

    One division per corner (``1/det``; ``2t/|A|^2``, ``2t/|adj A|^2``, ``2t/det`` are products of it).
    Measured on this 2-core CPU (float32, warm, minimum of 5 runs, value and gradient with respect to the scaled
    free coordinates of L-BFGS, perturbed boxes): 0.8 / 9.5 / 130 ms at 10^3 / 30^3 / 60^3 elements against
    0.8 / 11.4 / 196 ms for `jax.grad` (the forward pass alone: 0.2 / 2.0 / 21 ms). What dominates: XLA:CPU does
    not fuse a kernel with 24 outputs per element into one loop; it materialises the gathered and permuted corner
    coordinates and recomputes the shared corner quantities per output (barriers, per-element rows and chunking
    with `lax.map` were measured and are not faster); past the caches (60^3: 7 MB per corner array) it is
    memory-bound. Summing into the nodes: see `jaxci.metrics.incidence` (its forms measured by
    scripts/bench_kernel.py).

    **Arguments:** `points` of shape ``(n, 3)``; `conn` the transposed connectivity ``(8, N)``; `weight`
    optional ``(N,)``: 1 for a real element, 0 for a padding one (`jaxci.optim._buckets`), which then adds
    nothing to F, its max or its gradient, and F is the mean over the real corners (default: every element);
    `power` (static) p: the p-mean `pmean_objective` and its gradient instead of F (default None: F).

    **Returns:** ``(F, kmax, grad)``: scalars (``inf`` if any corner has det <= 0) and shape ``(n, 3)`` (the
    contributions of inverted corners are left out).

    `block` (static): evaluate F and its gradient over blocks of this many elements (`_terms_and_grad_blocks`;
    default `grad_block`: `GRAD_BLOCK` above `GRAD_BLOCK_FROM` elements on a CPU, larger on an accelerator, else 0:
    the whole mesh at once), where the mesh has
    more elements than that and `power` is None (the p-mean needs every corner's excess before any gradient:
    always at once). Same values to rounding.

    `n_corners` (with `weight`, F only, no blocks): what F and its gradient are divided by instead of the real
    corners of `conn` (the default); 1 gives their sums, as one device's share of a sharded mesh needs
    (`jaxci.optim.sharding.sharded_terms_and_grad` divides the exchanged sums by the whole mesh's count).

    `incidence`: how the per-element node gradients reach the nodes (`jaxci.metrics.incidence`): None (default)
    by 24 scatter-adds, else `jaxci.metrics.incidence.node_incidence` of `conn` (and `weight`) for a gather over
    each node's incident slots or a sorted segment sum, padding elements never summed into a node. Built once
    per problem and passed in (an argument of the compiled function, not a constant in it).
    """
    if block is None:
        block = grad_block(int(conn.shape[1]))
    block = int(block)
    if power is None and 0 < block < conn.shape[1] and n_corners is None:
        return _terms_and_grad_blocks(points, conn, weight, block, incidence)
    return _terms_and_grad(jnp, points, conn, weight, power, n_corners, incidence)


def objective_terms_and_grad_np(points: np.ndarray, conn: np.ndarray, power: float | None = None
                                ) -> tuple[float, float, np.ndarray]:
    """`objective_terms_and_grad` in numpy (the dtype of `points`; no compilation): ``(F, kmax, grad)``; with
    `power` p the p-mean objective instead of F (`pmean_objective`).

    For meshes small enough that XLA's compilation costs more than the whole solve (`jaxci.optim.host`)."""
    f, kmax, g = _terms_and_grad(np, points, conn, None, power)
    return float(f), float(kmax), g


def pmean_objective(points, hexes, power: float) -> float:
    """The p-mean objective ``M_p = (mean_i e_i^p)^(1/p)`` over every hexahedron corner, ``e_i = (kappa_i/3)^2 - 1``
    (F of Eq. 3.1 is ``M_1``): numpy float64; ``inf`` if a corner is inverted.

    As p grows the worst corners weigh more (``M_p -> max e_i``): minimising it pulls the worst element where
    the mean lets it be (on a hexahedral sphere the mean objective made the worst element worse).
    """
    pts = np.asarray(points, dtype=np.float64)
    conn = np.ascontiguousarray(np.asarray(hexes).T)
    det, fro2, adj2 = corner_invariants(*corner_columns(*gather_corners(pts, conn, np)))
    valid = det > 0
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        idet = np.where(valid, 1.0 / np.where(valid, det, 1.0), 0.0)  # as `objective_terms_and_grad` forms it
        term = np.where(valid, fro2 * adj2 * idet * idet * (1.0 / 9.0), np.inf)
        return float(pmean_weights(np, term - 1.0, None, float(power))[0])


def _corner_parts(xp, points, conn, columns=None):
    """The corner quantities of the closed-form gradient: columns a, b, c, their cross products u, v, w, |A|^2,
    |adj A|^2, 1/det (0 where det <= 0), its square and (kappa/3)^2 (``inf`` where det <= 0), each ``(8, N)``.
    `columns`: optional ``(x, y, z)`` coordinate arrays of `points`, each ``(n,)`` (formed once for many calls)."""
    pt = points.T if columns is None else columns
    X, Y, Z = (xp.stack([pt[d][conn[a]] for a in range(8)]) for d in range(3))
    ax, ay, az, bx, by, bz, cx, cy, cz = corner_columns(X, Y, Z)
    a, b, c = (ax, ay, az), (bx, by, bz), (cx, cy, cz)
    u, v, w = _cross(b, c), _cross(c, a), _cross(a, b)
    det = a[0] * u[0] + a[1] * u[1] + a[2] * u[2]
    fro2 = sum(t * t for t in (*a, *b, *c))
    adj2 = sum(t * t for t in (*u, *v, *w))
    valid = det > 0
    # one division per corner: t = fro2 adj2 / (9 det^2), and 2 t / fro2, 2 t / adj2, 2 t / det are products
    idet = xp.where(valid, 1.0 / xp.where(valid, det, 1.0), 0.0)
    idet2 = idet * idet
    term = xp.where(valid, fro2 * adj2 * idet2 * (1.0 / 9.0), xp.inf)
    if xp is not np:
        term = jax.lax.optimization_barrier(term)
    return (a, b, c, u, v, w, fro2, adj2, idet, idet2), term


def _node_grads(xp, parts, w2):
    """Per element node, the gradient of ``sum over corners of (9 w2 / 2) (kappa/3)^2`` from `_corner_parts`:
    three ``(8, N)`` arrays (x, y, z components), row m at local node m; `w2` a scalar or ``(N,)`` per element."""
    a, b, c, u, v, w, fro2, adj2, idet, idet2 = parts
    p = w2 * adj2 * idet2
    q = w2 * fro2 * idet2
    r = p * fro2 * idet
    vxc, bxw = _cross(v, c), _cross(b, w)
    cxu, wxa = _cross(c, u), _cross(w, a)
    uxb, axv = _cross(u, b), _cross(a, v)
    nodes = []
    for k in range(3):
        ga = p * a[k] + q * (vxc[k] + bxw[k]) - r * u[k]
        gb = p * b[k] + q * (cxu[k] + wxa[k]) - r * v[k]
        gc = p * c[k] + q * (uxb[k] + axv[k]) - r * w[k]
        nodes.append(-(ga + gb + gc) + _rows(xp, ga, _COLUMN_OWNER[0]) + _rows(xp, gb, _COLUMN_OWNER[1])
                     + _rows(xp, gc, _COLUMN_OWNER[2]))
    return nodes


def _terms_and_grad(xp, points, conn, weight, power=None, n_corners=None, incidence=None):
    """The body of `objective_terms_and_grad` with the array module `xp` (`jax.numpy` or `numpy`); `power`
    (static) p: the p-mean ``M_p`` of the excesses (`pmean_objective`) instead of their mean F; `n_corners` and
    `incidence` (JAX only) as there."""
    parts, term = _corner_parts(xp, points, conn)
    # the mean of term - 1 (small numbers near the optimum), not mean(term) - 1: in float32 over 8 M corners the
    # rounding of a sum of values near 1 swamped the decrease of F that the line search tests
    if weight is None:
        f = xp.mean(term - 1.0)
        kmax = xp.sqrt(xp.max(term))
        w2 = 2.0 / (9.0 * term.size)
        real = None
    else:
        real = weight > 0  # (N,): padding elements drop out of F, the max and (w2 = 0) the gradient
        if n_corners is None:
            n_corners = 8.0 * xp.sum(real.astype(term.dtype))
        f = xp.sum(xp.where(real, term - 1.0, 0.0)) / n_corners
        kmax = xp.sqrt(xp.max(xp.where(real, term, 0.0)))
        w2 = xp.where(real, 2.0 / (9.0 * n_corners), 0.0)
    if power is not None:  # the p-mean: each corner's gradient weighted by (e_i / M_p)^(p - 1)
        f, weights = pmean_weights(xp, term - 1.0, real, power)
        w2 = w2 * weights
    n = points.shape[0]
    nodes = _node_grads(xp, parts, w2)
    if xp is not np:
        return f, kmax, accumulate(nodes, conn, n, incidence)
    # one bincount per component: np.add.at is ~20x slower
    return f, kmax, np.stack([np.bincount(conn.reshape(-1), weights=node.reshape(-1), minlength=n)
                              .astype(points.dtype) for node in nodes], axis=1)


def _terms_and_grad_blocks(points, conn, weight, block: int, incidence=None):
    """`_terms_and_grad` (F, not the p-mean) over blocks of `block` elements in a `lax.fori_loop`: only one
    block's corner arrays are live. The last block starts at ``N - block`` (no padding, no copy of `conn`); its
    elements already counted by the block before get weight 0 in F and the max. Needs ``N >= block``.

    Without `incidence` each block's node gradients are scattered into the gradient carried through the loop;
    with one, they are written into per-element arrays ``(8, N)`` (the overlap of the last block rewrites the
    same values) and summed into the nodes once after the loop (`jaxci.metrics.incidence.accumulate`)."""
    n_el = conn.shape[1]
    n_blocks = -(-n_el // block)
    dtype = points.dtype
    if weight is None:
        n_corners = jnp.asarray(8.0 * n_el, dtype)
    else:
        n_corners = 8.0 * jnp.sum((weight > 0).astype(dtype))
    w2 = 2.0 / (9.0 * n_corners)
    n = points.shape[0]
    columns = tuple(points[:, d] for d in range(3))  # once, not per block

    def body(i, carry):
        s, m, grads = carry
        start = jnp.minimum(i * block, n_el - block)
        c = jax.lax.dynamic_slice_in_dim(conn, start, block, axis=1)
        new = start + jnp.arange(block, dtype=start.dtype) >= i * block
        real = jnp.ones(block, bool) if weight is None else jax.lax.dynamic_slice_in_dim(weight, start, block) > 0
        parts, term = _corner_parts(jnp, points, c, columns)
        s = s + jnp.sum(jnp.where(new & real, term - 1.0, 0.0))
        m = jnp.maximum(m, jnp.max(jnp.where(new & real, term, 0.0)))
        # masked elements' node gradients zeroed at the end: masking a corner input (a per-element w2 or 1/det)
        # instead was measured 3x slower (XLA then recomputes the corner quantities per output)
        if incidence is None:
            nodes = (jnp.where(new & real, t, 0.0) for t in _node_grads(jnp, parts, w2))
            grads = tuple(scatter_add(g, c, t) for g, t in zip(grads, nodes, strict=True))
        else:
            nodes = (jnp.where(real, t, 0.0) for t in _node_grads(jnp, parts, w2))
            grads = tuple(jax.lax.dynamic_update_slice_in_dim(g, t, start, axis=1)
                          for g, t in zip(grads, nodes, strict=True))
        return s, m, grads

    zero = jnp.zeros((), dtype)
    g0 = (jnp.zeros(n if incidence is None else conn.shape, dtype),) * 3
    s, m, grads = jax.lax.fori_loop(0, n_blocks, body, (zero, zero, g0))
    g = jnp.stack(grads, axis=1) if incidence is None else accumulate(grads, conn, n, incidence)
    return s / n_corners, jnp.sqrt(m), g
