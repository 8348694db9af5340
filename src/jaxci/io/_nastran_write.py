"""Write a mesh as a Nastran bulk data deck; `jaxci.io._nastran` reads it back.

**In place.** A mesh read from a Nastran deck carries the deck's text (field data ``nastran:deck``). When the mesh
still has the deck's GRIDs, element ids, cells and property ids (only the coordinates changed, as after
smoothing), `write_nastran` writes the deck again with only the coordinate fields of the GRIDs that moved
rewritten, each in the width and format it came in (8 characters in small field and in free field, 16 in large
field), as the text that reads back nearest to the new value (`jaxci.io._fields.format_real`; Nastran's short
exponents, ``1.2345-3``, where they gain a digit). A value its field cannot hold closely enough is refused with a
`MeshWriteError` naming the GRID (`jaxci.io._fields.REL_TOLERANCE`). Every other card, comment and line of the
deck, executive and case control included, is kept byte for byte (``INCLUDE`` files inlined).

**Afresh**, for any other mesh::

    $ jaxci mesh: 27 GRIDs, 8 elements
    GRID*                  1                              0.0             0.0
    *                    0.0
    CHEXA          1       1       1       2       5       4      10      11
    +             14      13
    ...
    ENDDATA

GRIDs in large field (16-character coordinates), elements in small field with the mesh's ids (8 digits at
most), ``CHEXA``/``CPENTA``/``CTETRA``/``CPYRAM`` (with their midside nodes), ``CQUAD4``, ``CTRIA3`` and ``CROD``,
property ids from the cell data ``nastran:pid`` (else the block number). Sets, other point and cell data, field
data and the cards of a source deck that could not be written in place are left out with a `LossyWriteWarning`,
issued before the file is written. A ``.dat`` file that a mesh read from an ANSYS file is written to is written as
APDL (`jaxci.io._ansys_apdl_write`).
"""

from __future__ import annotations

import os

import numpy as np

from ..mesh import HexMesh
from ._ansys_apdl_write import write_apdl
from ._fields import block_pids, fresh_coordinates, numbered_blocks
from ._losses import deck_text
from ._meshio import write_text
from ._nastran import parse_deck
from ._patran import named_blocks

#: (cell type, with midside nodes) -> element card written afresh.
CARD_NAMES = {("hexahedron", False): "CHEXA", ("hexahedron", True): "CHEXA", ("wedge", False): "CPENTA",
              ("wedge", True): "CPENTA", ("tetra", False): "CTETRA", ("tetra", True): "CTETRA",
              ("pyramid", False): "CPYRAM", ("pyramid", True): "CPYRAM", ("quad", False): "CQUAD4",
              ("triangle", False): "CTRIA3", ("line", False): "CROD"}
_MAX_ID = 99_999_999  # 8-character integer fields


def _small(name: str, fields: list[str]) -> list[str]:
    """A small-field card: 8 data fields on the first line, 8 on each continuation line (marked ``+``)."""
    rows = [fields[i : i + 8] for i in range(0, len(fields), 8)] or [[]]
    return [f"{name if k == 0 else '+':<8}" + "".join(f"{t:>8}" for t in row) for k, row in enumerate(rows)]


def _fresh(mesh: HexMesh, path: str) -> tuple[str, list[str]]:
    node_ids = np.arange(1, mesh.n_nodes + 1) if mesh.node_ids is None else np.asarray(mesh.node_ids, np.int64)
    named, lost = named_blocks(mesh, CARD_NAMES, "element card")
    blocks = [(card, ids, rows, block_pids(mesh, "nastran:pid", k, len(rows))) for card, rows, ids, k in named]
    numbered, all_ids = numbered_blocks(blocks, node_ids, path, "Nastran", "GRID", _MAX_ID,
                                        "Nastran's 8-character fields")
    out = [f"$ jaxci mesh: {mesh.n_nodes} GRIDs, {len(all_ids)} elements"]
    for nid, (x, y, z) in zip(node_ids.tolist(), fresh_coordinates(mesh, node_ids, path, "GRID", nastran=True),
                              strict=True):
        out += [f"GRID*   {nid:>16}{'':>16}{x:>16}{y:>16}", f"*       {z:>16}"]
    for card, ids, rows, pids in numbered:
        for eid, row, pid in zip(ids.tolist(), rows.tolist(), pids.tolist(), strict=True):
            nodes = ["" if n < 0 else str(node_ids[n]) for n in row]
            while nodes and not nodes[-1]:
                nodes.pop()
            out += _small(card, [str(eid), str(pid), *nodes])
    out.append("ENDDATA")
    return "\n".join(out) + "\n", lost


def write_nastran(mesh: HexMesh, path: str | os.PathLike) -> None:
    """Write `mesh` as a Nastran bulk data deck: its source deck with new coordinates when it has one, else afresh
    (module docstring).

    **Arguments:** `mesh` the mesh; `path` the file (`jaxci.io.write_mesh` passes a temporary name).

    **Returns:** nothing. Issues one `LossyWriteWarning` (before writing) listing what the deck leaves out; raises
    `MeshWriteError` for ids Nastran cannot hold or a coordinate its field cannot hold. `OSError` propagates.
    """
    path = os.fspath(path)
    deck = mesh.field_data.get("nastran:deck")
    if path.lower().endswith(".dat") and not isinstance(deck, str) and "ansys:deck" in mesh.field_data:
        write_apdl(mesh, path)  # an ANSYS .dat input file goes back as one
        return
    text, lost = deck_text(mesh, path, "nastran", _fresh, parse_deck, "GRID", nastran=True)
    write_text(path, text, "nastran", lost, "surrogateescape")
