"""Write a mesh as an Exodus II file; `jaxci.io._exodus` reads it back.

**In place.** A mesh read from an Exodus file carries the file's path (field data ``exodus:file``). When the mesh
still has the file's nodes, node ids, blocks, element ids and sets (only its coordinates changed, as after
smoothing), `write_exodus` copies the file and replaces only its coordinate variables (``coordx``/``coordy``/
``coordz``, or ``coord``) through the netCDF library: every other dimension, variable, attribute, set, map,
name, QA and info record and time step of results is the file's own, in the file's netCDF variant. The 6 face
nodes and the centroid of HEX27 bricks, which the mesh holds in no cell, are moved with their brick
(`jaxci.io._patran.serendipity_shift`). Coordinates stored as float32 are rounded to float32 (a
`LossyWriteWarning` says how far).

**Afresh**, for any other mesh (or a mesh whose source file is gone or no longer matches it): a netCDF 64-bit
offset file with the coordinates, one element block per cell block (``HEX8``, ``HEX20`` for bricks with every
midside node, ``WEDGE6``/``15``, ``TETRA4``/``10``, ``PYRAMID5``/``13``, ``SHELL4``/``8``/``9``,
``TRISHELL3``/``6``, ``BEAM2``/``3``, ``SPHERE``), named after the cell set that holds exactly that block, the node
and element ids as ``node_num_map`` / ``elem_num_map`` (ids up to 2147483647), and the point sets as node sets.
Point and cell data, field data, other cell sets and cells Exodus has no type for are left out with a
`LossyWriteWarning`, issued before the file is written.
"""

from __future__ import annotations

import os
import shutil
import warnings

import numpy as np

from ..errors import JaxciError, MeshWriteError
from ..mesh import HexMesh
from ._deck import element_ids, model_difference, refuse_bad_ids
from ._exodus import ExodusFile, read_exodus
from ._losses import dropped_data
from ._meshio import LossyWriteWarning, warn_lost
from ._patran import named_blocks, serendipity_shift

#: (cell type, with midside nodes) -> the Exodus element type written afresh.
EXODUS_NAMES = {
    ("hexahedron", False): "HEX8", ("hexahedron", True): "HEX20", ("wedge", False): "WEDGE6",
    ("wedge", True): "WEDGE15", ("tetra", False): "TETRA4", ("tetra", True): "TETRA10",
    ("pyramid", False): "PYRAMID5", ("pyramid", True): "PYRAMID13", ("quad", False): "SHELL4",
    ("quad8", False): "SHELL8", ("quad9", False): "SHELL9", ("triangle", False): "TRISHELL3",
    ("triangle6", False): "TRISHELL6", ("line", False): "BEAM2", ("line3", False): "BEAM3",
    ("vertex", False): "SPHERE",
}
_INT32 = 2**31 - 1


def _reference(src: str) -> tuple[ExodusFile | None, HexMesh | None, str | None]:
    """The source file read again, or why it cannot be."""
    if not os.path.isfile(src):
        return None, None, f"the source file {src} no longer exists"
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return ExodusFile(src), read_exodus(src), None
    except JaxciError as exc:
        return None, None, f"the source file can no longer be read ({exc})"


def _in_place(mesh: HexMesh, f: ExodusFile, ref: HexMesh, src: str, path: str) -> None:
    import netCDF4

    pts = np.array(mesh.points, dtype=np.float64)
    for _, _, _, cell, conn, _ in f.blocks:
        if cell == "hexahedron" and conn is not None and conn.shape[1] == 27 and len(conn):
            idx, new = serendipity_shift(ref.points, pts, conn)
            pts[idx.ravel()] = new.reshape(-1, 3)
    if f.float32:
        err = np.abs(pts.astype(np.float32).astype(np.float64) - pts).max(initial=0.0)
        if err > 0:
            warnings.warn(f"{os.path.basename(path)}: exodus rounds the coordinates to float32, as the source file "
                          f"stores them (by up to {err:.3g})", LossyWriteWarning, stacklevel=4)
    shutil.copyfile(src, path)
    try:
        with netCDF4.Dataset(path, "r+") as ds:
            ds.set_auto_mask(False)
            if "coord" in ds.variables:
                var = ds.variables["coord"]
                var[:] = pts[:, : var.shape[0]].T
            else:
                for k, c in enumerate("xyz"):
                    if f"coord{c}" in ds.variables:
                        ds.variables[f"coord{c}"][:] = pts[:, k]
    except (RuntimeError, ValueError) as exc:
        raise MeshWriteError(f"{path}: cannot write the coordinates into the copy of {src} ({exc})") from exc


def _chars(names: list[str], width: int) -> np.ndarray:
    out = np.zeros((len(names), width), "S1")
    for k, name in enumerate(names):
        raw = name.encode("utf-8")[: width - 1]
        out[k, : len(raw)] = np.frombuffer(raw, "S1")
    return out


def _plan(mesh: HexMesh, path: str) -> tuple[dict, list[str]]:
    """Everything a fresh file holds, and which cells and sets it leaves out (checked before anything is
    written)."""
    blocks, lost = named_blocks(mesh, EXODUS_NAMES, "Exodus element type")
    ids = [b[2] for b in blocks]
    elem_ids = element_ids(ids, [len(b[1]) for b in blocks])
    elem_ids = np.concatenate(elem_ids) if elem_ids else np.zeros(0, np.int64)
    node_ids = None if mesh.node_ids is None else np.asarray(mesh.node_ids, np.int64)
    keep_elem_map = any(i is not None for i in ids)
    refuse_bad_ids(path, [(a, w) for a, w in ((node_ids, "node"), (elem_ids if keep_elem_map else None, "element"))
                          if a is not None], "Exodus", _INT32, "this writer stores")
    written = {k for *_, k in blocks}
    names, named = [""] * len(blocks), set()
    for set_name, per_block in mesh.cell_sets.items():
        sizes = [len(np.unique(np.asarray(r, np.int64))) if r is not None else 0 for r in per_block]
        full = [k for k, n in enumerate(sizes) if n and n == len(mesh.cells[k].data)]
        if len(full) == 1 and sum(sizes) == sizes[full[0]] and full[0] in written:
            pos = [b[3] for b in blocks].index(full[0])
            if not names[pos]:
                names[pos] = set_name
                named.add(set_name)
    others = sorted(set(mesh.cell_sets) - named)
    if others:
        lost.append(f"cell sets {others} (only a set that is exactly one element block is kept, as its name)")
    plan = {"blocks": blocks, "names": names, "node_ids": node_ids,
            "elem_ids": elem_ids if keep_elem_map else None}
    return plan, lost


def _write_fresh(mesh: HexMesh, plan: dict, path: str) -> None:
    import netCDF4

    blocks, sets = plan["blocks"], list(mesh.point_sets.items())
    longest = max([len(n.encode()) for n in plan["names"]] + [len(n.encode()) for n, _ in sets] + [32])
    with netCDF4.Dataset(path, "w", format="NETCDF3_64BIT_OFFSET") as ds:
        ds.setncatts({"api_version": np.float32(8.0), "version": np.float32(8.0), "floating_point_word_size":
                      np.int32(8), "file_size": np.int32(1), "maximum_name_length": np.int32(longest),
                      "int64_status": np.int32(0),
                      "title": f"jaxci mesh: {mesh.n_nodes} nodes, {sum(len(b[1]) for b in blocks)} elements"})
        for name, size in (("len_string", 33), ("len_line", 81), ("four", 4), ("len_name", longest + 1),
                           ("time_step", None), ("num_dim", 3), ("num_nodes", mesh.n_nodes),
                           ("num_elem", sum(len(b[1]) for b in blocks)), ("num_el_blk", len(blocks))):
            ds.createDimension(name, size)
        ds.createVariable("time_whole", "f8", ("time_step",))
        names = ds.createVariable("coor_names", "S1", ("num_dim", "len_name"))
        names[:] = _chars(["X", "Y", "Z"], longest + 1)
        for k, c in enumerate("xyz"):
            ds.createVariable(f"coord{c}", "f8", ("num_nodes",))[:] = mesh.points[:, k]
        if plan["node_ids"] is not None:
            ds.createVariable("node_num_map", "i4", ("num_nodes",))[:] = plan["node_ids"]
        if plan["elem_ids"] is not None:
            ds.createVariable("elem_num_map", "i4", ("num_elem",))[:] = plan["elem_ids"]
        ds.createVariable("eb_status", "i4", ("num_el_blk",))[:] = np.ones(len(blocks), np.int32)
        prop = ds.createVariable("eb_prop1", "i4", ("num_el_blk",))
        prop.setncattr("name", "ID")
        prop[:] = np.arange(1, len(blocks) + 1)
        ds.createVariable("eb_names", "S1", ("num_el_blk", "len_name"))[:] = _chars(plan["names"], longest + 1)
        for k, (etype, conn, _, _) in enumerate(blocks, 1):
            ds.createDimension(f"num_el_in_blk{k}", len(conn))
            ds.createDimension(f"num_nod_per_el{k}", conn.shape[1])
            var = ds.createVariable(f"connect{k}", "i4", (f"num_el_in_blk{k}", f"num_nod_per_el{k}"))
            var.setncattr("elem_type", etype)
            var[:] = conn + 1
        if sets:
            ds.createDimension("num_node_sets", len(sets))
            ds.createVariable("ns_status", "i4", ("num_node_sets",))[:] = np.ones(len(sets), np.int32)
            prop = ds.createVariable("ns_prop1", "i4", ("num_node_sets",))
            prop.setncattr("name", "ID")
            prop[:] = np.arange(1, len(sets) + 1)
            ds.createVariable("ns_names", "S1", ("num_node_sets", "len_name"))[:] = \
                _chars([n for n, _ in sets], longest + 1)
            for k, (_, nodes) in enumerate(sets, 1):
                nodes = np.unique(np.asarray(nodes, np.int64))
                ds.createDimension(f"num_nod_ns{k}", len(nodes))
                ds.createVariable(f"node_ns{k}", "i4", (f"num_nod_ns{k}",))[:] = nodes + 1


def write_exodus(mesh: HexMesh, path: str | os.PathLike) -> None:
    """Write `mesh` as an Exodus II file: a copy of its source file with new coordinates when it has one, else
    afresh (module docstring).

    **Arguments:** `mesh` the mesh; `path` the file to write (`jaxci.io.write_mesh` passes a temporary name).

    **Returns:** nothing. Issues one `LossyWriteWarning` (before writing) listing what the file leaves out; raises
    `MeshWriteError` for ids Exodus cannot hold. `OSError` from writing propagates.
    """
    path = os.fspath(path)
    src = mesh.field_data.get("exodus:file")
    lost = []
    if isinstance(src, str):
        f, ref, reason = _reference(src)
        if ref is not None:
            reason = model_difference(mesh, ref)
        if reason is None:
            _in_place(mesh, f, ref, src, path)
            return
        lost.append(f"the results, QA and info records, attributes, maps and side sets of the source Exodus file "
                    f"{os.path.basename(src)} ({reason}, so it cannot be rewritten in place)")
    plan, more = _plan(mesh, path)
    lost += more + dropped_data(mesh, "exodus")
    warn_lost(path, "exodus", lost)
    _write_fresh(mesh, plan, path)
