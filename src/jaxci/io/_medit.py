"""Medit ``.mesh`` files (ASCII; INRIA's format, read and written by MMG, sfepy, Gmsh, TetGen): read and written.

A file is a list of sections: a keyword, then a count, then that many rows of numbers, each row ending with a
reference (an integer label). `read_medit` reads ``MeshVersionFormatted``, ``Dimension`` (3), ``Vertices``
(x y z ref), ``Hexahedra`` (8 nodes, VTK's order), ``Prisms`` (6: wedges), ``Pyramids`` (5), ``Tetrahedra`` (4),
``Quadrilaterals`` (4), ``Triangles`` (3), ``Edges`` (2) and ``Corners`` (vertex numbers), and skips every other
section (``Ridges``, ``RequiredVertices``, ``Normals``, ...: counted in `HexMesh.notes`). The references become
the point data ``medit:ref`` and the cell data ``medit:ref`` (one array per cell block), as meshio names them;
``Corners`` becomes the point set ``corners``. `write_medit` writes the same sections back (ASCII, version 2,
coordinates with 17 significant digits), references from ``medit:ref`` (else 0).

`MeshReadError` names the file and line of: a section cut short (the file ends before its rows do), a count or a
number that is not one, a vertex number out of range, ``Dimension`` other than 3, and a file without vertices.
"""

from __future__ import annotations

import os

import numpy as np

from ..errors import MeshReadError
from ..mesh import CellBlock, HexMesh
from ._deck import read_text
from ._meshio import file_cells, write_text

#: Medit section -> (cell type, nodes per row).
SECTIONS = {"Hexahedra": ("hexahedron", 8), "Prisms": ("wedge", 6), "Pyramids": ("pyramid", 5),
            "Tetrahedra": ("tetra", 4), "Quadrilaterals": ("quad", 4), "Triangles": ("triangle", 3),
            "Edges": ("line", 2)}
_BY_TYPE = {cell: name for name, (cell, _) in SECTIONS.items()}
#: Sections of other entities, with the number of values per row (skipped on reading).
_SKIPPED = {"Ridges": 1, "RequiredVertices": 1, "RequiredEdges": 1, "RequiredTriangles": 1,
            "RequiredQuadrilaterals": 1, "Normals": 3, "NormalAtVertices": 2, "Tangents": 3,
            "TangentAtVertices": 2, "Identifier": 0}


class _Tokens:
    """The whitespace-separated words of a file with the line of each (``#`` comments dropped)."""

    def __init__(self, text: str, path: str) -> None:
        self.words, self.lines, self.path = [], [], path
        for n, line in enumerate(text.splitlines(), 1):
            words = line.split("#", 1)[0].split()
            self.words += words
            self.lines += [n] * len(words)
        self.pos = 0

    def where(self, k: int | None = None) -> str:
        k = self.pos if k is None else k
        return f"{self.path}, line {self.lines[min(k, len(self.lines) - 1)]}" if self.lines else self.path

    def more(self) -> bool:
        return self.pos < len(self.words)

    def next(self) -> str:
        word = self.words[self.pos]
        self.pos += 1
        return word

    def count(self, section: str) -> int:
        if not self.more():
            raise MeshReadError(f"{self.where()}: the file ends after {section}, before its count (truncated?)")
        word = self.next()
        try:
            n = int(word)
        except ValueError:
            raise MeshReadError(f"{self.where(self.pos - 1)}: {section} count {word!r} is not an integer") from None
        if n < 0:
            raise MeshReadError(f"{self.where(self.pos - 1)}: {section} count {n} is negative")
        return n

    def table(self, section: str, n: int, width: int, kind) -> np.ndarray:
        start = self.pos
        if start + n * width > len(self.words):
            rows = (len(self.words) - start) // max(width, 1)
            raise MeshReadError(f"{self.where(start - 1)}: {section} announces {n} rows of {width} values but the "
                                f"file ends after {rows} (truncated?)")
        words = self.words[start : start + n * width]
        self.pos += n * width
        try:
            return np.array(words, dtype=kind).reshape(n, width)
        except ValueError:
            for k, w in enumerate(words):
                try:
                    kind(w)
                except ValueError:
                    raise MeshReadError(f"{self.where(start + k)}: {section}: {w!r} is not "
                                        f"{'an integer' if kind is np.int64 else 'a number'}") from None
            raise


def read_medit(path: str | os.PathLike) -> HexMesh:
    """Read an ASCII Medit ``.mesh`` file (module docstring).

    **Arguments:** `path` the file.

    **Returns:** a `HexMesh` with the cell blocks in file order, the references as ``medit:ref`` point and cell
    data, and the ``Corners`` as the point set ``corners``. Raises `MeshReadError` naming file and line.
    """
    path = os.fspath(path)
    text = read_text(path, "Medit mesh file")
    if "\0" in text[:4096]:
        raise MeshReadError(f"{path}: a binary file; jaxci reads ASCII Medit .mesh files (write .mesh, not .meshb)")
    tok = _Tokens(text, path)
    points = refs = None
    cells, cell_refs, skipped, corners = [], [], {}, None
    while tok.more():
        at = tok.pos
        word = tok.next()
        if word == "End":
            break
        if word == "MeshVersionFormatted":
            tok.count(word)
        elif word == "Dimension":
            dim = tok.count(word)
            if dim != 3:
                raise MeshReadError(f"{tok.where(at)}: Dimension {dim}; jaxci reads 3-D meshes")
        elif word == "Vertices":
            n = tok.count(word)
            table = tok.table(word, n, 4, np.float64)
            points, refs = table[:, :3], table[:, 3]
            if not np.isfinite(points).all():
                k = int(np.flatnonzero(~np.isfinite(points).all(axis=1))[0])
                raise MeshReadError(f"{path}: vertex {k + 1} has non-finite coordinates {points[k].tolist()}")
            if (refs != np.round(refs)).any():
                raise MeshReadError(f"{tok.where(at)}: Vertices: the references (4th column) must be integers")
        elif word in SECTIONS:
            cell, width = SECTIONS[word]
            n = tok.count(word)
            table = tok.table(word, n, width + 1, np.int64)
            if points is None:
                raise MeshReadError(f"{tok.where(at)}: {word} before Vertices")
            conn = table[:, :width]
            bad = (conn < 1) | (conn > len(points))
            if bad.any():
                r = int(np.flatnonzero(bad.any(axis=1))[0])
                raise MeshReadError(f"{tok.where(at)}: {word} row {r + 1} references vertex "
                                    f"{int(conn[r][bad[r]][0])}, but the file has vertices 1..{len(points)}")
            cells.append(CellBlock(cell, conn - 1))
            cell_refs.append(table[:, width])
        elif word == "Corners":
            n = tok.count(word)
            corners = tok.table(word, n, 1, np.int64).ravel() - 1
        elif word in _SKIPPED:
            n = tok.count(word)
            tok.table(word, n, _SKIPPED[word], np.float64)
            skipped[word] = n
        else:
            raise MeshReadError(f"{tok.where(at)}: unknown Medit keyword {word!r} (is this a Medit .mesh file?)")
    if points is None:
        raise MeshReadError(f"{path}: no Vertices section; not a Medit mesh file (or an empty one)")
    point_sets = {}
    if corners is not None:
        if len(corners) and (corners.min() < 0 or corners.max() >= len(points)):
            raise MeshReadError(f"{path}: Corners lists a vertex beyond the {len(points)} vertices")
        point_sets["corners"] = np.unique(corners)
    notes = [f"Medit sections jaxci does not model were skipped ({', '.join(sorted(skipped))})"] if skipped else []
    return HexMesh(points, tuple(cells), point_data={"medit:ref": refs.astype(np.int64)},
                   cell_data={"medit:ref": cell_refs}, point_sets=point_sets, source=path, notes=tuple(notes))


def write_medit(mesh: HexMesh, path: str | os.PathLike) -> None:
    """Write `mesh` as an ASCII Medit ``.mesh`` file (module docstring).

    **Arguments:** `mesh` the mesh; `path` the file (`jaxci.io.write_mesh` passes a temporary name).

    **Returns:** nothing. Issues one `LossyWriteWarning` (before writing) listing what Medit leaves out: cells of
    other types, ids, point sets other than ``corners``, cell sets, other data and field data.
    """
    path = os.fspath(path)
    lost = []
    cells = file_cells(mesh)
    ref_p = mesh.point_data.get("medit:ref")
    ref_p = np.zeros(mesh.n_nodes, np.int64) if ref_p is None else np.asarray(ref_p).astype(np.int64).ravel()
    ref_c = mesh.cell_data.get("medit:ref")
    out = ["MeshVersionFormatted 2", "", "Dimension 3", "", "Vertices", str(mesh.n_nodes)]
    out += [f"{x!r} {y!r} {z!r} {r}" for (x, y, z), r in zip(mesh.points.tolist(), ref_p.tolist(), strict=True)]
    for k, b in enumerate(cells):
        name = _BY_TYPE.get(b.type)
        if name is None:
            lost.append(f"{len(b.data)} {b.type} cells (no Medit section)")
            continue
        refs = np.asarray(ref_c[k]).astype(np.int64) if ref_c is not None and len(ref_c) == len(cells) else \
            np.zeros(len(b.data), np.int64)
        out += ["", name, str(len(b.data))]
        out += [" ".join(map(str, row)) + f" {r}" for row, r in zip((b.data + 1).tolist(), refs.tolist(),
                                                                     strict=True)]
    if "corners" in mesh.point_sets:
        c = np.unique(np.asarray(mesh.point_sets["corners"], np.int64)) + 1
        out += ["", "Corners", str(len(c)), *map(str, c.tolist())]
    out += ["", "End"]
    if mesh.node_ids is not None or any(b.ids is not None for b in cells):
        lost.append("node and element ids (nodes and elements are numbered from 1)")
    for what, d in (("point sets", {k for k in mesh.point_sets if k != "corners"}), ("cell sets", mesh.cell_sets),
                    ("point data", {k for k in mesh.point_data if k != "medit:ref"}),
                    ("cell data", {k for k in mesh.cell_data if k != "medit:ref"}), ("field data", mesh.field_data)):
        if d:
            lost.append(f"{what} {sorted(d)}")
    write_text(path, "\n".join(out) + "\n", "medit", lost)
