"""The real-mesh corpus of `scripts/bench_realmesh.py`: which meshes, where they are, and how the made ones are made.

Four sources, each mesh a `Entry` (name, path, where it came from, what it is):

- ``mesquite``: every hexahedral mesh of Mesquite's meshFiles in ``shared/data/mesquite/`` (read there, never
  copied: ``single_hex``, ``hexes_4by2by2``, ``large_box_hex_1000``, ``1000hex-block-internal-bias``,
  ``hex_5_tangled``, ``pave3``);
- ``peers``: ``cube9_pert`` and ``cube30_pert`` from ``shared/peers/`` (the unit cubes msqshape was measured on),
  and ``cube60_pert``, made here the same way (unit cube of 60^3 hexes, interior nodes moved uniformly by up to
  +-0.3 h per coordinate with ``numpy.random.default_rng(0)`` in node-index order, x fastest; the recipe
  reproduces ``cube9_pert.vtk`` bit for bit). Not in the default list (msqshape takes ~5 min on it): name it;
- ``cdb``: the ANSYS archives shipped in the ``mapdl-archive`` package that hold hexahedra (``HexBeam``: 40
  SOLID186 20-node bricks; ``academic_rotor``: 524 bricks; ``sector``: 101 bricks and 4 degenerate ones, wedges);
- ``gmsh``: meshes made with the ``gmsh`` wheel (curved boundaries, real-like), at each of ``sizes`` (target hex
  counts; ``small`` = 2,000, ``medium`` = 8,000, ``large`` = 25,000; the counts made are within ~30%):

  - ``sphere_tet2hex``: a unit ball, tetrahedra split into 4 hexahedra each (``Mesh.SubdivisionAlgorithm=2``):
    a poor unstructured all-hex mesh;
  - ``bracket_tet2hex``: an L-bracket (base plate and upright) with three bolt holes, split the same way;
  - ``torus_tet2hex``: a torus (radii 1 and 0.35), split the same way: doubly curved, its inner wall concave;
  - ``cylinder_ogrid``: a cylinder (radius 1, height 2), transfinite O-grid of 5 blocks (centre square and four
    curved blocks) recombined and extruded in layers: structured, curved boundary;
  - ``annulus_quad``: a thick tube (radii 0.5 and 1), unstructured quadrilaterals (Blossom full-quad
    recombination) swept along z in layers;
  - ``plate_holes_quad``: a 4 x 2 plate with three holes of different radii, meshed and swept the same way.

Made meshes go to ``--corpus-dir`` (default ``~/.cache/jaxci/realmesh``; never into the repository) as legacy
ASCII VTK (4.2, float64 exact, right-handed VTK node order), named after the shape, size and generator version, and
are reused when already there. Generation is deterministic (gmsh single-threaded, fixed seeds).

    python scripts/realmesh_corpus.py [--corpus-dir DIR] [--sizes small large] [--meshes NAME ...] [--list]

prints one line per mesh (name, hexes, nodes, inverted hexes and max kappa/3 as read by `jaxci.io.read_mesh`).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import io
import math
import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
MESQUITE = SHARED / "data" / "mesquite"
PEERS = SHARED / "peers"
DEFAULT_CORPUS_DIR = Path(os.path.expanduser("~")) / ".cache" / "jaxci" / "realmesh"
#: Bumped whenever a generator changes what it makes (it is part of the file names, so old files are not reused).
GENERATOR_VERSION = 1

SIZES = {"tiny": 300, "small": 2000, "medium": 8000, "large": 25000}
DEFAULT_SIZES = ("small", "large")

MESQUITE_FILES = {
    "single_hex": "single_hex.vtk",
    "hexes_4by2by2": "hexes_4by2by2.vtk",
    "large_box_hex_1000": "large_box_hex_1000.vtk",
    "1000hex-block-internal-bias": "1000hex-block-internal-bias.vtk",
    "hex_5_tangled": "hex_5_tangled.vtk",
    "pave3": "pave3.e.vtk",
}
CDB_FILES = {"cdb-HexBeam": "HexBeam.cdb", "cdb-academic_rotor": "academic_rotor.cdb", "cdb-sector": "sector.cdb"}
GMSH_SHAPES = ("sphere_tet2hex", "bracket_tet2hex", "torus_tet2hex", "cylinder_ogrid", "annulus_quad",
               "plate_holes_quad")


@dataclasses.dataclass(frozen=True)
class Entry:
    """One corpus mesh. `make` (None for a file that exists) writes `path`; `optional` ones are left out of the
    default list (named with ``--meshes`` they are made)."""

    name: str
    source: str  # mesquite | peers | cdb | gmsh
    path: Path
    description: str
    make: Callable[[Path], None] | None = None
    optional: bool = False
    target_hexes: int | None = None

    def ensure(self) -> Path:
        """The mesh file, made first if needed (atomically: a half-written file is never left under `path`)."""
        if self.make is not None and not self.path.exists():
            self.path.parent.mkdir(parents=True, exist_ok=True)
            tmp = self.path.with_name(self.path.stem + f".tmp{os.getpid()}" + self.path.suffix)
            try:
                self.make(tmp)
                os.replace(tmp, self.path)
            finally:
                if tmp.exists():
                    tmp.unlink()
        return self.path


def have_gmsh() -> bool:
    try:
        import gmsh  # noqa: F401
    except (ImportError, OSError):
        return False
    return True


def cdb_folder() -> Path | None:
    """The ``examples`` folder of the installed ``mapdl-archive`` package, or None."""
    try:
        import mapdl_archive
    except ImportError:
        return None
    d = Path(mapdl_archive.__file__).parent / "examples"
    return d if d.is_dir() else None


def size_target(size: str | int) -> tuple[str, int]:
    """``"small"`` -> ("small", 2000); ``"5000"`` / 5000 -> ("5000", 5000)."""
    if isinstance(size, str) and size in SIZES:
        return size, SIZES[size]
    try:
        n = int(size)
    except ValueError:
        raise SystemExit(f"unknown size {size!r}: one of {', '.join(SIZES)} or a hex count") from None
    if n < 50:
        raise SystemExit(f"size {n}: at least 50 hexahedra")
    return str(n), n


def entries(corpus_dir: str | os.PathLike | None = None, sizes: Sequence[str | int] = DEFAULT_SIZES) -> list[Entry]:
    """Every corpus entry (files not made yet: `Entry.ensure` makes them). Entries whose source is missing (no
    gmsh, no mapdl-archive, no shared folder) are left out."""
    cdir = Path(corpus_dir) if corpus_dir else DEFAULT_CORPUS_DIR
    out: list[Entry] = []
    for name, fname in MESQUITE_FILES.items():
        p = MESQUITE / fname
        if p.exists():
            out.append(Entry(name, "mesquite", p, f"Mesquite meshFiles {fname}"))
    for n in (9, 30):
        p = PEERS / f"cube{n}_pert.vtk"
        if p.exists():
            out.append(Entry(f"cube{n}_pert", "peers", p, f"unit cube {n}^3, interior perturbed 0.3 h, rng 0"))
    out.append(Entry("cube60_pert", "peers", cdir / f"cube60_pert-v{GENERATOR_VERSION}.vtk",
                     "unit cube 60^3, interior perturbed 0.3 h, rng 0 (made like cube9/cube30_pert)",
                     make=lambda path: write_vtk(path, *perturbed_cube(60)), optional=True))
    folder = cdb_folder()
    if folder is not None:
        for name, fname in CDB_FILES.items():
            if (folder / fname).exists():
                out.append(Entry(name, "cdb", folder / fname, f"mapdl-archive example {fname}"))
    if have_gmsh():
        for size in sizes:
            label, target = size_target(size)
            for shape in GMSH_SHAPES:
                path = cdir / f"{shape}-{label}-v{GENERATOR_VERSION}.vtk"

                def make(path, shape=shape, target=target):
                    write_vtk(path, *make_gmsh(shape, target))

                out.append(Entry(f"{shape}-{label}", "gmsh", path, f"gmsh {shape}, target {target} hexes",
                                 make=make, target_hexes=target))
    return out


def select(all_entries: list[Entry], names: Sequence[str] | None) -> list[Entry]:
    """The entries named (exact names, or a shape name for all its sizes, or a source: mesquite, peers, cdb, gmsh),
    or the non-optional ones when `names` is empty."""
    if not names:
        return [e for e in all_entries if not e.optional]
    chosen: list[Entry] = []
    for n in names:
        hit = [e for e in all_entries if n in (e.name, e.source) or e.name.split("-")[0] == n
               or (e.source == "gmsh" and e.name.rsplit("-", 1)[0] == n)]
        if not hit:
            raise SystemExit(f"unknown mesh {n!r}; known: {', '.join(e.name for e in all_entries)} "
                             f"(or a source: mesquite, peers, cdb, gmsh)")
        chosen += [e for e in hit if e not in chosen]
    return chosen


# ------------------------------------------------------------------------------------------------ writing
def orient(points: np.ndarray, hexes: np.ndarray) -> np.ndarray:
    """`hexes` with every left-handed element (negative sum of corner determinants) mirrored to VTK's order."""
    p = points[hexes]
    det = 0.0
    nb = ((1, 3, 4), (2, 0, 5), (3, 1, 6), (0, 2, 7), (7, 5, 0), (4, 6, 1), (5, 7, 2), (6, 4, 3))
    for i, (a, b, c) in enumerate(nb):
        det = det + np.einsum("ij,ij->i", p[:, a] - p[:, i], np.cross(p[:, b] - p[:, i], p[:, c] - p[:, i]))
    out = hexes.copy()
    left = det < 0
    out[left] = hexes[left][:, [4, 5, 6, 7, 0, 1, 2, 3]]
    return out


def compact(points: np.ndarray, hexes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drop nodes no hexahedron uses (renumbering in the old order)."""
    used = np.unique(hexes)
    if len(used) == len(points):
        return points, hexes
    new = np.full(len(points), -1, dtype=np.int64)
    new[used] = np.arange(len(used))
    return points[used], new[hexes]


def write_vtk(path: Path, points: np.ndarray, hexes: np.ndarray) -> None:
    """Legacy ASCII VTK 4.2 (what msqshape and jaxci both read), float64 exact."""
    import meshio

    write_ascii_vtk(path, meshio.Mesh(np.asarray(points, dtype=np.float64), [("hexahedron", hexes)]))


def write_ascii_vtk(path: Path, mesh) -> None:
    """meshio's legacy VTK 4.2 writer, ``binary=False``, without its console note about ASCII files."""
    import meshio

    with contextlib.redirect_stderr(io.StringIO()):
        meshio.vtk.write(str(path), mesh, "4.2", binary=False)


# ------------------------------------------------------------------------------------------------ cubes
def perturbed_cube(n: int, amplitude: float = 0.3, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Unit cube of n^3 hexahedra, nodes x fastest, interior nodes moved by U(-amplitude h, amplitude h) per
    coordinate (``default_rng(seed)``, one ``(n_interior, 3)`` draw in node-index order): ``cube{n}_pert.vtk``."""
    g = np.linspace(0.0, 1.0, n + 1)
    z, y, x = np.meshgrid(g, g, g, indexing="ij")
    pts = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    inner = ((pts > 1e-12) & (pts < 1 - 1e-12)).all(axis=1)
    h = 1.0 / n
    pts[inner] += np.random.default_rng(seed).uniform(-amplitude * h, amplitude * h, size=(int(inner.sum()), 3))
    i, j, k = (a.ravel() for a in np.meshgrid(np.arange(n), np.arange(n), np.arange(n), indexing="ij"))
    i, j, k = k, j, i  # element order x fastest, like the nodes
    m = n + 1

    def node(a, b, c):
        return a + m * (b + m * c)

    hexes = np.stack([node(i, j, k), node(i + 1, j, k), node(i + 1, j + 1, k), node(i, j + 1, k),
                      node(i, j, k + 1), node(i + 1, j, k + 1), node(i + 1, j + 1, k + 1), node(i, j + 1, k + 1)],
                     axis=1).astype(np.int64)
    return pts, hexes


# ------------------------------------------------------------------------------------------------ gmsh
class _Gmsh:
    """gmsh initialised quietly, single-threaded (deterministic), finalised on exit."""

    def __enter__(self):
        import gmsh

        gmsh.initialize(["gmsh"], readConfigFiles=False)
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.Verbosity", 1)
        gmsh.option.setNumber("General.NumThreads", 1)
        gmsh.option.setNumber("Mesh.RandomSeed", 1)
        gmsh.model.add("m")
        return gmsh

    def __exit__(self, *exc):
        import gmsh

        gmsh.finalize()


def _occ_model(gmsh, build: Callable, h: float) -> None:
    """The OCC geometry `build(occ)` makes, synchronised, with a uniform mesh size `h`."""
    build(gmsh.model.occ)
    gmsh.model.occ.synchronize()
    gmsh.option.setNumber("Mesh.MeshSizeMin", h)
    gmsh.option.setNumber("Mesh.MeshSizeMax", h)


def _nodes(gmsh) -> tuple[np.ndarray, dict]:
    tags, coords, _ = gmsh.model.mesh.getNodes()
    pts = np.asarray(coords, dtype=np.float64).reshape(-1, 3)
    return pts, {int(t): i for i, t in enumerate(tags)}


def _elements(gmsh, dim: int, n_nodes_per: int, index: dict) -> np.ndarray:
    """The elements of dimension `dim` with `n_nodes_per` nodes (linear hex 8, quad 4), as point indices; error if
    elements of another type are there."""
    blocks = []
    for et in gmsh.model.mesh.getElementTypes(dim):
        name, _, _, nn, _, _ = gmsh.model.mesh.getElementProperties(et)
        _, enodes = gmsh.model.mesh.getElementsByType(et)
        if nn != n_nodes_per:
            if len(enodes):
                raise RuntimeError(f"gmsh made {len(enodes) // nn} {name} elements (only {n_nodes_per}-node wanted)")
            continue
        lut = np.vectorize(index.__getitem__, otypes=[np.int64])
        blocks.append(lut(np.asarray(enodes, dtype=np.int64)).reshape(-1, nn))
    return np.concatenate(blocks) if blocks else np.zeros((0, n_nodes_per), dtype=np.int64)


def _solid_tet2hex(build: Callable, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Tetrahedralise the OCC solid `build(occ)` makes with size `h`, split every tet into 4 hexahedra."""
    with _Gmsh() as gmsh:
        _occ_model(gmsh, build, h)
        gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 12)
        gmsh.option.setNumber("Mesh.Algorithm3D", 1)  # Delaunay
        gmsh.option.setNumber("Mesh.SubdivisionAlgorithm", 2)  # all hexahedra
        gmsh.model.mesh.generate(3)
        pts, index = _nodes(gmsh)
        hexes = _elements(gmsh, 3, 8, index)
    return pts, hexes


def _sphere(occ) -> None:
    occ.addSphere(0, 0, 0, 1.0)


def _bracket(occ) -> None:
    base = occ.addBox(0, 0, 0, 4.0, 2.0, 0.5)
    up = occ.addBox(0, 0, 0, 0.5, 2.0, 2.5)
    solid, _ = occ.fuse([(3, base)], [(3, up)])
    holes = [occ.addCylinder(2.0, 0.6, -0.1, 0, 0, 0.7, 0.3), occ.addCylinder(3.2, 1.4, -0.1, 0, 0, 0.7, 0.35),
             occ.addCylinder(-0.1, 1.0, 1.6, 0.7, 0, 0, 0.4)]
    occ.cut(solid, [(3, t) for t in holes])


def _torus(occ) -> None:
    occ.addTorus(0, 0, 0, 1.0, 0.35)


def _quads(build: Callable, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Unstructured all-quad mesh of the OCC surface `build(occ)` makes (frontal-Delaunay for quads, Blossom
    full-quad recombination), size `h`: ``(points (n, 2), quads (m, 4))`` counter-clockwise."""
    with _Gmsh() as gmsh:
        _occ_model(gmsh, build, h)
        gmsh.option.setNumber("Mesh.Algorithm", 8)
        gmsh.option.setNumber("Mesh.RecombineAll", 1)
        gmsh.option.setNumber("Mesh.RecombinationAlgorithm", 3)
        gmsh.model.mesh.generate(2)
        if any(gmsh.model.mesh.getElementProperties(t)[3] != 4 for t in gmsh.model.mesh.getElementTypes(2)):
            gmsh.model.mesh.clear()  # triangles left (a coarse size): split every cell into quadrilaterals instead
            gmsh.option.setNumber("Mesh.MeshSizeMin", 2 * h)
            gmsh.option.setNumber("Mesh.MeshSizeMax", 2 * h)
            gmsh.option.setNumber("Mesh.SubdivisionAlgorithm", 1)
            gmsh.model.mesh.generate(2)
        pts, index = _nodes(gmsh)
        quads = _elements(gmsh, 2, 4, index)
    pts, quads = compact(pts, quads)
    p = pts[quads]
    area = 0.5 * np.sum(p[:, :, 0] * np.roll(p[:, :, 1], -1, 1) - np.roll(p[:, :, 0], -1, 1) * p[:, :, 1], axis=1)
    quads[area < 0] = quads[area < 0][:, ::-1]
    return pts[:, :2], quads


def _sweep(pts2: np.ndarray, quads: np.ndarray, thickness: float, layers: int) -> tuple[np.ndarray, np.ndarray]:
    """Extrude a counter-clockwise quad mesh along +z in `layers` equal layers: right-handed hexahedra."""
    n = len(pts2)
    z = np.linspace(0.0, thickness, layers + 1)
    pts = np.concatenate([np.column_stack([pts2, np.full(n, zk)]) for zk in z])
    hexes = np.concatenate([np.column_stack([quads + k * n, quads + (k + 1) * n]) for k in range(layers)])
    return pts, hexes


def _annulus(occ) -> None:
    outer = occ.addDisk(0, 0, 0, 1.0, 1.0)
    inner = occ.addDisk(0, 0, 0, 0.5, 0.5)
    occ.cut([(2, outer)], [(2, inner)])


def _plate(occ) -> None:
    plate = occ.addRectangle(0, 0, 0, 4.0, 2.0)
    holes = [occ.addDisk(0.9, 1.0, 0, 0.3, 0.3), occ.addDisk(2.1, 0.8, 0, 0.45, 0.45),
             occ.addDisk(3.3, 1.2, 0, 0.25, 0.25)]
    occ.cut([(2, plate)], [(2, t) for t in holes])


SWEPT = {"annulus_quad": (_annulus, 0.5), "plate_holes_quad": (_plate, 0.4)}


def _swept(shape: str, h: float) -> tuple[np.ndarray, np.ndarray]:
    build, thickness = SWEPT[shape]
    pts2, quads = _quads(build, h)
    p = pts2[quads]
    area = 0.5 * np.abs(np.sum(p[:, :, 0] * np.roll(p[:, :, 1], -1, 1) - np.roll(p[:, :, 0], -1, 1) * p[:, :, 1], 1))
    hq = math.sqrt(float(area.mean()))  # mean quad edge: layers about as thick
    return _sweep(pts2, quads, thickness, max(2, round(thickness / hq)))


def _ogrid(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Cylinder radius 1, height 2: transfinite O-grid (centre square of half-width 0.45 with n x n cells, four
    curved blocks n x m, radial cells growing outward by 1.1) recombined and extruded in layers (gmsh built-in
    kernel)."""
    r, a, height = 1.0, 0.45, 2.0
    m = max(2, round(0.6 * n))
    layers = max(2, round(height / (2 * a / n) / 1.5))
    with _Gmsh() as gmsh:
        g = gmsh.model.geo
        c = g.addPoint(0, 0, 0)
        sq = [g.addPoint(a * sx, a * sy, 0) for sx, sy in ((1, 1), (-1, 1), (-1, -1), (1, -1))]
        s = r / math.sqrt(2)
        ci = [g.addPoint(s * sx, s * sy, 0) for sx, sy in ((1, 1), (-1, 1), (-1, -1), (1, -1))]
        side = [g.addLine(sq[i], sq[(i + 1) % 4]) for i in range(4)]
        arc = [g.addCircleArc(ci[i], c, ci[(i + 1) % 4]) for i in range(4)]
        rad = [g.addLine(sq[i], ci[i]) for i in range(4)]
        surfs = [g.addPlaneSurface([g.addCurveLoop(side)])]
        for i in range(4):
            j = (i + 1) % 4
            surfs.append(g.addPlaneSurface([g.addCurveLoop([side[i], rad[j], -arc[i], -rad[i]])]))
        for t in side + arc:  # the geo kernel's own mesh constraints (a later synchronize keeps them)
            g.mesh.setTransfiniteCurve(t, n + 1)
        for t in rad:
            g.mesh.setTransfiniteCurve(t, m + 1, "Progression", 1.1)
        for t in surfs:
            g.mesh.setTransfiniteSurface(t)
            g.mesh.setRecombine(2, t)
        g.extrude([(2, t) for t in surfs], 0, 0, height, numElements=[layers], recombine=True)
        g.synchronize()
        gmsh.model.mesh.generate(3)
        pts, index = _nodes(gmsh)
        hexes = _elements(gmsh, 3, 8, index)
    return pts, hexes


#: shape -> (make(h) -> (points, hexes), h giving about 5,000 hexes, exponent of hexes in 1/h)
_TET2HEX = {"sphere_tet2hex": (_sphere, 0.25), "bracket_tet2hex": (_bracket, 0.36), "torus_tet2hex": (_torus, 0.2)}


def make_gmsh(shape: str, target: int) -> tuple[np.ndarray, np.ndarray]:
    """Points and right-handed VTK-ordered hexahedra of `shape` with about `target` hexahedra (deterministic:
    the size is refined at most twice from a fixed first guess)."""
    if shape == "cylinder_ogrid":
        def count(n):
            m = max(2, round(0.6 * n))
            return (n * n + 4 * n * m) * max(2, round(2.0 / (0.9 / n) / 1.5))

        n = min(range(2, 80), key=lambda k: abs(count(k) - target))
        pts, hexes = _ogrid(n)
    else:
        if shape in _TET2HEX:
            build, h5k = _TET2HEX[shape]

            def make(h):
                return _solid_tet2hex(build, h)
        elif shape in SWEPT:
            h5k = {"annulus_quad": 0.05, "plate_holes_quad": 0.085}[shape]

            def make(h):
                return _swept(shape, h)
        else:
            raise ValueError(f"unknown gmsh shape {shape!r}")
        h = h5k * (5000.0 / target) ** (1 / 3)
        for _ in range(3):
            pts, hexes = make(h)
            ratio = len(hexes) / target
            if 0.75 <= ratio <= 1.33:
                break
            h *= ratio ** (1 / 3)
    pts, hexes = compact(pts, hexes)
    return pts, orient(pts, hexes)


# ------------------------------------------------------------------------------------------------ CLI
def describe(entry: Entry) -> dict:
    """Read `entry` with jaxci and return its size and quality as read (float64)."""
    from jaxci.io import read_mesh
    from jaxci.metrics.report import quality_report

    mesh = read_mesh(entry.ensure())
    rep = quality_report(mesh)
    return dict(name=entry.name, source=entry.source, path=str(entry.path), hexes=mesh.n_hexes,
                nodes=mesh.n_nodes, other_cells=rep.other_cells, inverted=rep.inverted_elements,
                max_condition=rep.max_condition, mean_condition=rep.mean_condition)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--corpus-dir", default=str(DEFAULT_CORPUS_DIR), help="where made meshes go (default %(default)s)")
    ap.add_argument("--sizes", nargs="+", default=list(DEFAULT_SIZES),
                    help=f"gmsh mesh sizes: {', '.join(f'{k}={v}' for k, v in SIZES.items())} or hex counts")
    ap.add_argument("--meshes", nargs="+", help="names (default: all but the optional cube60_pert)")
    ap.add_argument("--list", action="store_true", help="list the names only (make nothing)")
    args = ap.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)
    chosen = select(entries(args.corpus_dir, args.sizes), args.meshes)
    if not have_gmsh():
        print("note: gmsh is not installed (pip install gmsh): no gmsh meshes", file=sys.stderr)
    for e in chosen:
        if args.list:
            print(f"{e.name:32s} {e.source:8s} {e.path}")
            continue
        d = describe(e)
        mc = "-" if d["max_condition"] is None else f"{d['max_condition']:.4g}"
        print(f"{d['name']:32s} {d['source']:8s} hexes {d['hexes']:7d} nodes {d['nodes']:7d} "
              f"inverted {d['inverted']:5d} max k/3 {mc:>9s}  {e.path}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
