"""Read Exodus II files (``.e``, ``.exo``, ``.ex2``, ``.g``): Cubit's, MOOSE's, Sierra's and SEACAS's mesh format.

An Exodus II file is a netCDF file (classic, 64-bit offset, CDF-5 or netCDF-4), read with the ``netCDF4`` package.
`read_exodus` reads:

- the node coordinates (``coordx``/``coordy``/``coordz``, or ``coord``), with the node ids of ``node_num_map``
  as `HexMesh.node_ids`;
- every element block (``connect1`` .. ``connectN``, ``elem_type``) as one cell block, in file order, with the
  element ids of ``elem_num_map`` as `CellBlock.ids` and the block's name (``eb_names``, else ``block_ID``) as a
  cell set. ``HEX``/``HEX8`` bricks are smoothed; ``HEX20`` and ``HEX27`` are bricks with midside nodes
  (`CellBlock.midside`, re-placed on their edges as for every quadratic brick); a HEX27's 6 face nodes and
  centroid are in no cell of the mesh (never moved by smoothing) and are re-placed by the Exodus writer
  (`jaxci.io._patran.serendipity_shift`: each keeps its offset from where the 20-node brick puts it).
  ``TETRA``/``WEDGE``/``PYRAMID`` blocks (4/6/5 nodes; 10/15/13 with midside nodes) are as in every other format.
  ``SHELL``/``QUAD``, ``TRI``/``TRISHELL``, ``BEAM``/``BAR``/``TRUSS`` and ``SPHERE``/``CIRCLE`` blocks are kept as
  ``quad``/``triangle``/``line``/``vertex`` cells (and their quadratic forms), never smoothed; blocks of any other
  type stay in the file but are not part of the mesh (counted in `HexMesh.notes`);
- node sets (``node_ns*``) as point sets named by ``ns_names`` (else ``nodeset_ID``), and side sets
  (``elem_ss*``/``side_ss*``) as point sets of the nodes of their sides (name from ``ss_names``, else
  ``sideset_ID``; `jaxci.smooth`'s ``fixed_sets`` / ``--fixed-set`` can fix them) and as face sets
  (`HexMesh.face_sets`: the boundary classification keeps the border of each a feature curve, so a surface a
  load or condition is given on keeps its extent);
- the nodes of every block that is not a volume block (shells, beams, spheres, unmodelled types) as
  `HexMesh.held_nodes`: smoothing never moves them.

The time steps of results, QA and info records, attributes, distribution factors, maps and properties are not read;
they stay in the file, and `jaxci.io._exodus_write.write_exodus` copies the file and replaces only its coordinates.
The mesh carries the file's path as the field data ``exodus:file`` for that. Every read error is a
`MeshReadError` naming the file and the block, set or variable: a file cut short (`jaxci.io._netcdf`), a block
referencing node numbers beyond ``num_nodes``, ids given twice in a number map, a set naming missing nodes or
elements.
"""

from __future__ import annotations

import os
import re

import numpy as np

from ..cells import EDGES
from ..errors import MeshReadError
from ..mesh import CellBlock, HexMesh
from ._deck import first_duplicate
from ._netcdf import classic_shortfall
from ._patran import NODE_COUNTS, split_solid

#: Exodus element type family (the name without its node count) -> jaxci volume cell type.
VOLUME_FAMILIES = {"HEX": "hexahedron", "HEXAHEDRON": "hexahedron", "TETRA": "tetra", "TET": "tetra",
                   "WEDGE": "wedge", "PYRAMID": "pyramid", "PYRA": "pyramid"}
#: Exodus family -> {nodes per element: meshio cell type} of the kept, never smoothed blocks.
OTHER_FAMILIES = {
    **{f: {4: "quad", 8: "quad8", 9: "quad9"} for f in ("SHELL", "QUAD")},
    **{f: {3: "triangle", 6: "triangle6"} for f in ("TRI", "TRIANGLE", "TRISHELL")},
    **{f: {2: "line", 3: "line3"} for f in ("BEAM", "BAR", "TRUSS", "EDGE")},
    **{f: {1: "vertex"} for f in ("SPHERE", "CIRCLE")},
}
#: 1-based local nodes of each side of the volume cells (Exodus side numbering) and of shells.
SIDES = {
    "hexahedron": ((1, 2, 6, 5), (2, 3, 7, 6), (3, 4, 8, 7), (1, 5, 8, 4), (1, 4, 3, 2), (5, 6, 7, 8)),
    "wedge": ((1, 2, 5, 4), (2, 3, 6, 5), (1, 4, 6, 3), (1, 3, 2), (4, 5, 6)),
    "tetra": ((1, 2, 4), (2, 3, 4), (1, 4, 3), (1, 3, 2)),
    "pyramid": ((1, 2, 5), (2, 3, 5), (3, 4, 5), (4, 1, 5), (1, 4, 3, 2)),
    "quad": ((1, 2, 3, 4), (1, 4, 3, 2), (1, 2), (2, 3), (3, 4), (4, 1)),
    "triangle": ((1, 2, 3), (1, 3, 2), (1, 2), (2, 3), (3, 1)),
}


def classify_block(elem_type: str, nodes: int) -> str | None:
    """The jaxci / meshio cell type of an Exodus element type name and its node count, or None when jaxci does not
    model it."""
    m = re.match(r"[A-Z]+", elem_type.strip().upper())
    family = m.group(0) if m else ""
    if family in VOLUME_FAMILIES:
        cell = VOLUME_FAMILIES[family]
        corners, full = NODE_COUNTS[cell]
        return cell if nodes in (corners, full) or (cell == "hexahedron" and nodes == 27) else None
    return OTHER_FAMILIES.get(family, {}).get(nodes)


def _names(ds, var: str, count: int, prefix: str, ids) -> list[str]:
    names = [""] * count
    if var in ds.variables and count:
        raw = np.asarray(ds.variables[var][:])
        names = [b"".join(row).split(b"\0")[0].decode("utf-8", "replace").strip() for row in raw.reshape(count, -1)]
    return [n or f"{prefix}_{int(i)}" for n, i in zip(names, ids, strict=True)]


def _dim(ds, name: str) -> int:
    return len(ds.dimensions[name]) if name in ds.dimensions else 0


def _ints(ds, var: str, where: str) -> np.ndarray:
    if var not in ds.variables:
        raise MeshReadError(f"{where}: variable {var} is missing")
    return np.asarray(ds.variables[var][:]).astype(np.int64)


class ExodusFile:
    """What jaxci reads of an Exodus II file (`read_exodus` builds the mesh from it)."""

    def __init__(self, path: str) -> None:
        self.path = path
        _check_complete(path)
        import netCDF4

        try:
            ds = netCDF4.Dataset(path, "r")
        except (OSError, RuntimeError, ValueError) as exc:
            raise MeshReadError(f"{path}: not a readable Exodus II (netCDF) file ({_reason(exc)})") from None
        try:
            with ds:
                ds.set_auto_mask(False)
                self._read(ds)
        except MeshReadError:
            raise
        except (OSError, RuntimeError, ValueError, IndexError, KeyError, TypeError) as exc:
            raise MeshReadError(f"{path}: corrupt Exodus II file ({_reason(exc)})") from None

    def _read(self, ds) -> None:
        p = self.path
        self.n = n = _dim(ds, "num_nodes")
        if "num_nodes" not in ds.dimensions:
            raise MeshReadError(f"{p}: not an Exodus II mesh (netCDF file without a num_nodes dimension)")
        ndim = _dim(ds, "num_dim")
        if "coord" in ds.variables:
            xyz = np.asarray(ds.variables["coord"][:], np.float64).reshape(ndim, n).T
        else:
            names = [f"coord{c}" for c in "xyz"[:ndim]]
            missing = [v for v in names if v not in ds.variables]
            if missing:
                raise MeshReadError(f"{p}: variable {missing[0]} (node coordinates) is missing")
            xyz = np.stack([np.asarray(ds.variables[v][:], np.float64) for v in names], axis=1)
        self.points = np.zeros((n, 3))
        self.points[:, : xyz.shape[1]] = xyz[:, :3]
        self.float32 = any(ds.variables[v].dtype == np.float32 for v in ("coord", "coordx") if v in ds.variables)
        self.node_ids = self._map(ds, "node_num_map", n, "node")
        self._blocks(ds)
        self.elem_ids = self._map(ds, "elem_num_map", self.n_elem, "element")
        self.point_sets, self.face_sets = {}, {}
        self._node_sets(ds)
        self._side_sets(ds)
        self.time_steps = _dim(ds, "time_step")
        self.variables = {k: _dim(ds, f"num_{k}_var") for k in ("nod", "elem", "glo", "nset", "sset")}
        self.qa = _dim(ds, "num_qa_rec")

    def _map(self, ds, var: str, count: int, what: str) -> np.ndarray | None:
        if var not in ds.variables:
            return None
        ids = _ints(ds, var, f"{self.path}: {var}")
        if len(ids) != count:
            raise MeshReadError(f"{self.path}: {var} has {len(ids)} entries for {count} {what}s")
        if len(ids) and ids.min() < 1:
            k = int(np.argmin(ids))
            raise MeshReadError(f"{self.path}: {var} gives {what} {k + 1} the id {ids[k]}; ids must be positive")
        if (dup := first_duplicate(ids)) is not None:
            raise MeshReadError(f"{self.path}: {var} gives the id {ids[dup[0]]} to {what}s {dup[0] + 1} and "
                                f"{dup[1] + 1}; ids must be unique")
        return ids

    def _blocks(self, ds) -> None:
        p, nblk = self.path, _dim(ds, "num_el_blk")
        block_ids = _ints(ds, "eb_prop1", p) if "eb_prop1" in ds.variables else np.arange(1, nblk + 1)
        names = _names(ds, "eb_names", nblk, "block", block_ids)
        self.blocks = []  # (block id, name, elem_type, cell type or None, connectivity (0-based) or None, offset)
        offset = 0
        for k in range(1, nblk + 1):
            bid, name = int(block_ids[k - 1]), names[k - 1]
            count = _dim(ds, f"num_el_in_blk{k}")
            var = ds.variables.get(f"connect{k}")
            if var is None:
                if count:
                    raise MeshReadError(f"{p}: element block {bid} ({name}) has {count} elements but no connect{k}")
                self.blocks.append((bid, name, "", None, None, offset))
                continue
            etype = str(getattr(var, "elem_type", "") or "")
            conn = np.asarray(var[:]).astype(np.int64).reshape(count, -1)
            bad = (conn < 1) | (conn > self.n)
            if bad.any():
                row = int(np.flatnonzero(bad.any(axis=1))[0])
                raise MeshReadError(f"{p}: element {row + 1} of block {bid} ({name}, {etype}) references node "
                                    f"{int(conn[row][bad[row]][0])}, but the file has nodes 1..{self.n} "
                                    f"({int(bad.any(axis=1).sum())} such elements)")
            self.blocks.append((bid, name, etype, classify_block(etype, conn.shape[1]), conn - 1, offset))
            offset += count
        self.n_elem = offset
        if "num_elem" in ds.dimensions and _dim(ds, "num_elem") != offset:
            raise MeshReadError(f"{p}: num_elem is {_dim(ds, 'num_elem')} but the blocks hold {offset} elements")

    def _node_sets(self, ds) -> None:
        count = _dim(ds, "num_node_sets")
        ids = _ints(ds, "ns_prop1", self.path) if "ns_prop1" in ds.variables else np.arange(1, count + 1)
        for k, name in enumerate(_names(ds, "ns_names", count, "nodeset", ids), 1):
            nodes = _ints(ds, f"node_ns{k}", self.path) if _dim(ds, f"num_nod_ns{k}") else np.zeros(0, np.int64)
            bad = (nodes < 1) | (nodes > self.n)
            if bad.any():
                raise MeshReadError(f"{self.path}: node set {int(ids[k - 1])} ({name}) lists node {nodes[bad][0]}, "
                                    f"but the file has nodes 1..{self.n}")
            self.point_sets[name] = np.unique(nodes - 1)

    def _side_sets(self, ds) -> None:
        count = _dim(ds, "num_side_sets")
        ids = _ints(ds, "ss_prop1", self.path) if "ss_prop1" in ds.variables else np.arange(1, count + 1)
        starts = np.array([b[5] for b in self.blocks] + [self.n_elem])
        for k, name in enumerate(_names(ds, "ss_names", count, "sideset", ids), 1):
            where = f"{self.path}: side set {int(ids[k - 1])} ({name})"
            if not _dim(ds, f"num_side_ss{k}"):
                elems = sides = np.zeros(0, np.int64)
            else:
                elems, sides = _ints(ds, f"elem_ss{k}", where), _ints(ds, f"side_ss{k}", where)
            bad = (elems < 1) | (elems > self.n_elem)
            if bad.any():
                raise MeshReadError(f"{where} lists element {elems[bad][0]}, but the file has elements "
                                    f"1..{self.n_elem}")
            nodes, faces = [np.zeros(0, np.int64)], [np.zeros((0, 4), np.int64)]
            block = np.searchsorted(starts, elems - 1, side="right") - 1
            for b in np.unique(block).tolist():
                bid, bname, etype, cell, conn, start = self.blocks[b]
                sel = block == b
                n_b, f_b = _sides(conn, cell, elems[sel] - 1 - start, sides[sel], f"{where}, block {bid}")
                nodes.append(n_b)
                faces.append(f_b)
            self.face_sets[name] = np.concatenate(faces)
            if name in self.point_sets:
                name = f"{name} (side set)"
            self.point_sets[name] = np.unique(np.concatenate(nodes))


def _sides(conn, cell, rows, sides, where) -> tuple[np.ndarray, np.ndarray]:
    """The given sides (1-based side numbers) of rows of a block: their nodes (the side's corner nodes and the
    midside nodes of its edges; every node of an element whose type has no side table), and the faces among
    them, ``(k, 4)`` corner nodes (a triangle repeats its last node; edges of shells are no faces)."""
    no_faces = np.zeros((0, 4), np.int64)
    if conn is None:
        return np.zeros(0, np.int64), no_faces
    family = "quad" if cell in ("quad", "quad8", "quad9") else "triangle" if cell in ("triangle", "triangle6") \
        else cell
    table = SIDES.get(family)
    if table is None:
        return conn[rows].ravel(), no_faces
    bad = (sides < 1) | (sides > len(table))
    if bad.any():
        raise MeshReadError(f"{where}: side {sides[bad][0]} of a {cell} element; it has sides 1..{len(table)}")
    out, faces = [], [no_faces]
    corners = NODE_COUNTS[cell][0] if cell in NODE_COUNTS else {"quad": 4, "triangle": 3}[family]
    data, mid = conn[:, :corners], None
    if cell in NODE_COUNTS and conn.shape[1] > corners:
        data, mid = split_solid(conn[:, : NODE_COUNTS[cell][1]], cell)
    for s, local in enumerate(table, 1):
        sel = rows[sides == s]
        if not len(sel):
            continue
        idx = np.array(local) - 1
        out.append(data[sel][:, idx].ravel())
        if len(idx) >= 3:
            faces.append(data[sel][:, np.r_[idx, idx[-1]][:4]])
        if mid is not None:
            on = [e for e, (a, b) in enumerate(EDGES[cell].tolist()) if a in idx and b in idx]
            out.append(mid[sel][:, on].ravel())
    return (np.concatenate(out) if out else np.zeros(0, np.int64)), np.concatenate(faces)


def _reason(exc: BaseException) -> str:
    return " ".join(str(exc).split())[:160] or type(exc).__name__


def _check_complete(path: str) -> None:
    try:
        short = classic_shortfall(path)
    except ValueError as exc:
        raise MeshReadError(f"{path}: corrupt or truncated netCDF file: {exc}") from None
    except OSError as exc:
        raise MeshReadError(f"{path}: cannot read ({exc.strerror})") from None
    if short:
        raise MeshReadError(f"{path}: truncated Exodus II file: its variables need {short} bytes more than the file "
                            f"holds (cut short while copying or writing?)")


def read_exodus(path: str | os.PathLike) -> HexMesh:
    """Read an Exodus II file.

    **Arguments:** `path` the file (any extension; the netCDF library finds its variant).

    **Returns:** a `HexMesh` (module docstring for what it holds) with ``source`` the file and the field data
    ``exodus:file``. Raises `MeshReadError` naming the file and the block, set or map that is wrong.
    """
    path = os.fspath(path)
    f = ExodusFile(path)
    cells, cell_sets, notes, other, held = [], {}, [], {}, [np.zeros(0, np.int64)]
    for bid, name, etype, cell, conn, start in f.blocks:
        if name in cell_sets:
            name = f"{name} (block {bid})"
        if conn is None:
            continue
        if cell not in VOLUME_FAMILIES.values():  # shells, beams, spheres, unknown blocks: their nodes stay
            held.append(conn.ravel())
        if cell is None:
            key = f"{etype or '?'} ({conn.shape[1]} nodes)"
            other[key] = other.get(key, 0) + len(conn)
            continue
        ids = None if f.elem_ids is None else f.elem_ids[start : start + len(conn)]
        if cell in NODE_COUNTS:
            data, mid = split_solid(conn[:, : NODE_COUNTS[cell][1]] if conn.shape[1] == 27 else conn, cell)
        else:
            data, mid = conn, None
        cells.append(CellBlock(cell, data, ids, mid))
        cell_sets[name] = len(cells) - 1
    if other:
        listed = ", ".join(f"{n} {t}" for t, n in sorted(other.items()))
        notes.append(f"element blocks of types jaxci does not model ({listed}) stay in the file but are not part of "
                     f"the mesh; their nodes are never moved")
    hex27 = sum(len(b[4]) for b in f.blocks if b[3] == "hexahedron" and b[4] is not None and b[4].shape[1] == 27)
    if hex27:
        notes.append(f"{hex27} HEX27 bricks: smoothed as 20-node bricks; their face and centre nodes are re-placed "
                     f"when the mesh is written back to Exodus (keeping their offsets)")
    if f.time_steps or any(f.variables.values()):
        kinds = {"nod": "nodal", "elem": "element", "glo": "global", "nset": "node set", "sset": "side set"}
        nv = ", ".join(f"{v} {kinds[k]}" for k, v in f.variables.items() if v)
        notes.append(f"{f.time_steps} time steps of results ({nv or 'no'} variables) stay in the file; only a write "
                     f"back to Exodus keeps them")
    if f.float32:
        notes.append("coordinates are stored as float32 in the file")
    sets = {name: [np.arange(len(b.data)) if k == i else np.zeros(0, np.int64) for k, b in enumerate(cells)]
            for name, i in cell_sets.items()}
    held_nodes = np.unique(np.concatenate(held))
    return HexMesh(f.points, tuple(cells), point_sets=f.point_sets, cell_sets=sets, node_ids=f.node_ids,
                   field_data={"exodus:file": path}, face_sets=f.face_sets,
                   held_nodes=held_nodes if len(held_nodes) else None, source=path, notes=tuple(notes))
