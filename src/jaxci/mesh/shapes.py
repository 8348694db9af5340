"""Hexahedral meshes of simple non-box shapes, for testing boundary classification and projection.

- `l_block`: an L-shaped prism (a box with one quarter removed): a re-entrant (concave) feature edge.
- `bevelled_box`: a box with one edge replaced by a chamfer of planar facets: mild feature angles.
- `annulus`: a hollow cylinder: curved surfaces and circular feature curves without corners.

All hexahedra are right-handed in VTK node order.
"""

from __future__ import annotations

import numpy as np

from ..errors import MeshError
from . import HexMesh, hex_mesh
from .generate import grid_hexes


def _compact(points: np.ndarray, hexes: np.ndarray) -> HexMesh:
    """A mesh of the used nodes only (renumbered in their original order)."""
    used = np.unique(hexes)
    new = np.full(len(points), -1, dtype=np.int64)
    new[used] = np.arange(len(used))
    return hex_mesh(points[used], new[hexes])


def l_block(n: int = 2, *, size: float = 1.0, nz: int | None = None) -> HexMesh:
    """An L-shaped prism: the box ``[0, 2s] x [0, 2s] x [0, s]`` without the quarter ``x > s, y > s``.

    **Arguments:** `n` elements per length `size` (so ``2n x 2n x nz`` cells minus a quarter); `size` s;
    `nz` elements along z (default `n`).

    **Returns:** a `HexMesh` of ``3 n^2 nz`` hexahedra. Its re-entrant edge is the line ``x = y = s``.
    """
    if int(n) != n or n < 1:
        raise MeshError(f"l_block: n must be a positive integer, got {n!r}")
    n = int(n)
    nz = n if nz is None else int(nz)
    m = 2 * n
    h = size / n
    k, j, i = np.meshgrid(np.arange(nz + 1), np.arange(m + 1), np.arange(m + 1), indexing="ij")
    points = np.stack([i.ravel() * h, j.ravel() * h, k.ravel() * size / nz], axis=1).astype(np.float64)
    hexes = grid_hexes(m, m, nz)
    ci, cj = hexes[:, 0] % (m + 1), (hexes[:, 0] // (m + 1)) % (m + 1)
    keep = ~((ci >= n) & (cj >= n))
    return _compact(points, hexes[keep])


def bevelled_box(
    n: int = 6, *, bevel: float = 0.3, n_facets: int = 2, facet_cells: int = 1, length: float = 1.0
) -> HexMesh:
    """The unit box with its edge ``x = z = 1`` (along y) replaced by `n_facets` planar chamfer facets.

    The cross-section (the x-z plane) is the unit square whose corner (1, 1) is cut from (1, 1 - bevel) to
    (1 - bevel, 1) by a convex polyline of `n_facets` equal segments, so that each of the ``n_facets + 1`` edges
    along y (face x=1 | facet | ... | face z=1) is a turn of ``90 / (n_facets + 1)`` degrees: 30 degrees with
    the default two facets. The section is meshed by discrete transfinite (Coons) interpolation of its
    boundary, the square's corner node landing on the middle of the polyline; then extruded along y.

    **Arguments:**

    - `n`: elements per side of the section and along y.
    - `bevel`: the length cut off both sides of the corner (0 < bevel < 1).
    - `n_facets`: number of chamfer facets (an even number puts the square's corner node on a facet vertex).
    - `facet_cells`: elements per facet.
    - `length`: the extent along y.

    **Returns:** a `HexMesh` of ``n^3`` hexahedra.
    """
    if n_facets < 1 or n_facets % 2 or not 0 < bevel < 1 or n_facets * facet_cells // 2 >= n:
        raise MeshError(
            f"bevelled_box: needs an even n_facets >= 2, 0 < bevel < 1 and n > n_facets*facet_cells/2, got "
            f"n={n}, bevel={bevel}, n_facets={n_facets}, facet_cells={facet_cells}"
        )
    turn = np.radians(90.0 / (n_facets + 1))
    angles = turn * np.arange(1, n_facets + 1)  # outward normal angle of each facet, from +x towards +z
    dirs = np.stack([-np.sin(angles), np.cos(angles)], axis=1)  # along each facet, from x=1 towards z=1
    seg = bevel / dirs[:, 1].sum()
    verts = np.array([1.0, 1.0 - bevel]) + seg * np.concatenate([[[0.0, 0.0]], np.cumsum(dirs, axis=0)])
    t = np.linspace(0.0, 1.0, facet_cells + 1)[:-1, None]
    # polyline nodes from (1, 1-bevel) to (1-bevel, 1)
    fine = np.concatenate([a + t * (b - a) for a, b in zip(verts[:-1], verts[1:], strict=True)] + [verts[-1:]])
    m = n_facets * facet_cells // 2  # boundary nodes of each square side taken by the polyline
    straight = np.linspace(0.0, 1.0 - bevel, n - m + 1)
    right = np.concatenate([np.stack([np.ones(n - m), straight[:-1]], axis=1), fine[: m + 1]])  # x=1, z up
    top = np.concatenate([np.stack([straight[:-1], np.ones(n - m)], axis=1), fine[m:][::-1]])  # z=1, x up
    s = np.linspace(0.0, 1.0, n + 1)
    left = np.stack([np.zeros(n + 1), s], axis=1)
    bottom = np.stack([s, np.zeros(n + 1)], axis=1)
    si, tj = s[:, None, None], s[None, :, None]
    sec = (
        (1 - si) * left[None, :, :]
        + si * right[None, :, :]
        + (1 - tj) * bottom[:, None, :]
        + tj * top[:, None, :]
        - ((1 - si) * (1 - tj) * bottom[0] + si * (1 - tj) * bottom[-1] + (1 - si) * tj * top[0] + si * tj * top[-1])
    )  # (i, j, 2): x-z coordinates of section node (i, j)
    ys = np.linspace(0.0, length, n + 1)
    # grid axes (i: x, j: z, k: y) are left-handed in xyz; use (i, k=y, j=z) ordering: node (i, y, z)
    xs = np.broadcast_to(sec[:, None, :, 0], (n + 1, n + 1, n + 1))
    zs = np.broadcast_to(sec[:, None, :, 1], (n + 1, n + 1, n + 1))
    yy = np.broadcast_to(ys[None, :, None], (n + 1, n + 1, n + 1))
    # flatten with i fastest, then y, then z: index i + (n+1) * (iy + (n+1) * iz)
    points = np.stack([a.transpose(2, 1, 0).ravel() for a in (xs, yy, zs)], axis=1)
    return hex_mesh(points, grid_hexes(n, n, n))


def annulus(
    n_theta: int = 24,
    n_r: int = 2,
    n_z: int = 2,
    *,
    r_inner: float = 0.5,
    r_outer: float = 1.0,
    height: float = 1.0,
) -> HexMesh:
    """A hollow cylinder (annulus extruded along z), meshed in polar coordinates.

    Nodes lie exactly on the circles ``r = r_inner + (r_outer - r_inner) i / n_r`` at angles
    ``2 pi j / n_theta`` and heights ``height k / n_z``. Adjacent faces of a cylinder turn by ``360 / n_theta``
    degrees, below the default 40 degree feature angle for ``n_theta >= 10``.

    **Arguments:** `n_theta` elements around, `n_r` across the wall, `n_z` along the axis; radii and height.

    **Returns:** a `HexMesh` of ``n_theta n_r n_z`` hexahedra.
    """
    if n_theta < 3 or n_r < 1 or n_z < 1 or not 0 < r_inner < r_outer:
        raise MeshError(
            f"annulus: needs n_theta >= 3, n_r >= 1, n_z >= 1 and 0 < r_inner < r_outer, got {n_theta}, {n_r}, "
            f"{n_z}, {r_inner}, {r_outer}"
        )
    k, j, i = np.meshgrid(np.arange(n_z + 1), np.arange(n_theta), np.arange(n_r + 1), indexing="ij")
    r = r_inner + (r_outer - r_inner) * i.ravel() / n_r
    th = 2.0 * np.pi * j.ravel() / n_theta
    points = np.stack([r * np.cos(th), r * np.sin(th), height * k.ravel() / n_z], axis=1).astype(np.float64)
    return hex_mesh(points, grid_hexes(n_r, n_theta, n_z, periodic_j=True))
