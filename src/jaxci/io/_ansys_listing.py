"""Read the text that ANSYS APDL's NLIST and ELIST print (the paper's input).

Both listings are paged: a title block (`` LIST ALL SELECTED NODES.   DSYS=      0``), page headers
(`` *** ANSYS - ENGINEERING ANALYSIS SYSTEM  RELEASE 2020 R2 ... ***`` with version, date and time lines, the
job title) repeated on every page, then column headers and rows:

```
    NODE        X             Y             Z           THXY     THYZ     THZX
        1   0.0000000000       0.0000000000       0.0000000000          0.00     0.00     0.00

    ELEM MAT TYP REL ESY SEC        NODES
       1   1   1   1   0   1      1     2     5     4    10    11    14    13
```

A section starts at its column header (``NODE X Y Z ...`` or ``ELEM MAT TYP REL ESY SEC NODES``) and lasts until
the other header, so both listings may sit in one file (the paper saved both into one text file) and page
breaks may fall anywhere. Lines with any word that is not a number (headers, titles, dates) are skipped, except
a line of four or more fields led by a row number and at least half numbers, which is a corrupt data row (an
error); a line made only of numbers is a data row and is checked strictly:

- a node row has exactly as many fields as its column header (``NODE X Y Z`` and, if listed, ``THXY THYZ THZX``);
  coordinates may be in any float notation (``0.10000E-01``);
- an element row has ELEM MAT TYP REL ESY SEC and the 8 nodes I..P (14 integers). A 20-node SOLID186 brick
  continues its node list on following lines indented past the SEC column: its first 8 nodes are the corners
  I..P, the other 12 its midside nodes Q..B (kept with the element: see `jaxci.io._ansys`).

Nodes must be listed in the global Cartesian system (``DSYS=0``).
"""

from __future__ import annotations

import os
import re

import numpy as np

from ..errors import MeshReadError
from ..mesh import HexMesh
from ._ansys import Bricks, to_hexmesh
from ._deck import MAX_ID, is_number, parse_id, read_text
from ._fields import parse_real

_NODE_HEADER = ("NODE", "X", "Y", "Z")
_ELEM_HEADER = ("ELEM", "MAT", "TYP", "REL", "ESY", "SEC")
_ELEM_FIELDS = len(_ELEM_HEADER) + 8
_DSYS = re.compile(r"\bDSYS\s*=\s*(-?\d+)")


def _int(tok: str, path, lineno: int, what: str) -> int:
    try:
        value = int(tok)
    except ValueError:
        raise MeshReadError(f"{path}, line {lineno}: {what} {tok!r} is not an integer") from None
    if abs(value) > MAX_ID:
        raise MeshReadError(f"{path}, line {lineno}: {what} {value} is too large (jaxci reads numbers up to "
                            f"{MAX_ID})")
    return value


class _Rows:
    """Node and element rows collected from one or more listing files."""

    def __init__(self) -> None:
        self.files: list[str] = []
        self.nodes: list[tuple[int, float, float, float]] = []
        self.node_src: list[tuple[int, int]] = []
        self.elems: list[list[int]] = []  # ELEM MAT TYP REL ESY SEC nodes...
        self.elem_src: list[tuple[int, int]] = []

    def scan(self, path: str) -> None:
        fi = len(self.files)
        self.files.append(path)
        section, width, cont_col = None, 0, 0
        for lineno, raw in enumerate(read_text(path, "ANSYS listing").splitlines(), 1):
            raw = raw.expandtabs()
            toks = raw.split()
            if not toks:
                continue
            if tuple(toks[:4]) == _NODE_HEADER:
                section, width = "node", len(toks)
                continue
            if tuple(toks[:6]) == _ELEM_HEADER:
                section, cont_col = "elem", raw.index("SEC") + 3
                continue
            if (m := _DSYS.search(raw)) and int(m.group(1)) != 0:
                raise MeshReadError(
                    f"{path}, line {lineno}: nodes are listed in coordinate system DSYS={m.group(1)}; list them "
                    f"in the global Cartesian system (DSYS,0 before NLIST)"
                )
            numbers = sum(map(is_number, toks))
            if section is not None and toks[0].isdigit() and len(toks) >= 4 and len(toks) > numbers >= len(toks) / 2:
                # mostly numbers, led by a row number: a data row with a corrupt field, not a title
                bad = next(t for t in toks if not is_number(t))
                raise MeshReadError(f"{path}, line {lineno}: {section if section == 'node' else 'element'} row with "
                                    f"a field that is not a number ({bad!r}): corrupt listing")
            if section is None or not all(map(is_number, toks)) or (toks == ["1"] and raw[0] == "1"):
                continue  # page header, title, date, Fortran page eject, or numbers before any column header
            if section == "node":
                if len(toks) != width:
                    raise MeshReadError(
                        f"{path}, line {lineno}: node row has {len(toks)} fields, expected {width} "
                        f"(NODE X Y Z{' THXY THYZ THZX' if width == 7 else ''})"
                    )
                where = f"{path}, line {lineno}"
                nid = parse_id(toks[0], where, "node number")
                xyz = [parse_real(t, where, f"coordinate {c} of node {nid}") for c, t in
                       zip("XYZ", toks[1:4], strict=True)]
                self.nodes.append((nid, *xyz))
                self.node_src.append((fi, lineno))
            elif len(raw) - len(raw.lstrip()) >= cont_col:  # continuation of a 20-node element's node list
                if not self.elems or self.elem_src[-1][0] != fi:
                    raise MeshReadError(f"{path}, line {lineno}: node continuation line before any element row")
                self.elems[-1].extend(_int(t, path, lineno, "node number") for t in toks)
            else:
                if len(toks) != _ELEM_FIELDS:
                    raise MeshReadError(
                        f"{path}, line {lineno}: element row has {len(toks)} fields, expected {_ELEM_FIELDS} "
                        f"(ELEM MAT TYP REL ESY SEC and the 8 nodes I J K L M N O P)"
                    )
                row = [_int(t, path, lineno, f"field {k} ({name})") for k, (t, name) in
                       enumerate(zip(toks, _ELEM_HEADER + tuple("IJKLMNOP"), strict=True), 1)]
                parse_id(toks[0], f"{path}, line {lineno}", "element number")
                self.elems.append(row)
                self.elem_src.append((fi, lineno))

    def bricks(self) -> Bricks:
        n_midside = 0
        for row, (fi, lineno) in zip(self.elems, self.elem_src, strict=True):
            n = len(row) - len(_ELEM_HEADER)
            if n not in (8, 20):
                raise MeshReadError(
                    f"{self.files[fi]}, line {lineno}: element {row[0]} has {n} nodes; expected 8 (SOLID185) or "
                    f"20 (SOLID186 brick)"
                )
            n_midside += n == 20
        nodes = np.array(self.nodes, dtype=np.float64).reshape(-1, 4)
        elems = np.array([row[:_ELEM_FIELDS] for row in self.elems], dtype=np.int64).reshape(-1, _ELEM_FIELDS)
        midside = np.array([row[_ELEM_FIELDS:] if len(row) > _ELEM_FIELDS else [0] * 12 for row in self.elems],
                           dtype=np.int64).reshape(-1, 12)
        return Bricks(
            node_ids=np.array([row[0] for row in self.nodes], dtype=np.int64),
            points=nodes[:, 1:],
            elem_ids=elems[:, 0],
            attrs=elems[:, 1:6],
            corners=elems[:, 6:],
            files=tuple(self.files),
            node_src=np.array(self.node_src, dtype=np.int64).reshape(-1, 2),
            elem_src=np.array(self.elem_src, dtype=np.int64).reshape(-1, 2),
            n_midside=n_midside,
            midside=midside if (midside != 0).any() else None,
        )


def read_ansys_listing(nlist_path: str | os.PathLike, elist_path: str | os.PathLike | None = None) -> HexMesh:
    """Read a mesh from the text of ANSYS APDL's ``NLIST`` (nodes) and ``ELIST`` (elements).

    **Arguments:**

    - `nlist_path`: the saved NLIST output, or one file holding both listings.
    - `elist_path`: the saved ELIST output; None (default) when `nlist_path` holds both. Sections are found by
      their column headers, so either file may hold either listing.

    **Returns:** a `HexMesh` with ANSYS node numbers as `node_ids`, element numbers as block `ids`, MAT TYP REL
    ESY SEC as cell data ``ansys:mat`` ... ``ansys:sec``, and degenerate bricks turned into ``wedge``,
    ``pyramid`` and ``tetra`` blocks (counted in `notes`). Its `source` is the file, or ``"NLIST + ELIST"``.

    Raises `MeshReadError` naming the file and line for a malformed row, a node an element references but the
    NLIST lacks, or a missing NLIST or ELIST section.
    """
    files = [os.fspath(nlist_path)]
    if elist_path is not None and os.fspath(elist_path) != files[0]:
        files.append(os.fspath(elist_path))
    rows = _Rows()
    for path in files:
        rows.scan(path)
    if not rows.nodes:
        raise MeshReadError(
            f"{files[0]}: no NLIST node rows found (they follow a column header 'NODE X Y Z ...')"
        )
    if not rows.elems:
        hint = "save the ELIST output into the same file" if len(files) == 1 else "is it the ELIST output?"
        raise MeshReadError(
            f"{files[-1]}: node rows but no ELIST section (column header 'ELEM MAT TYP REL ESY SEC NODES'); "
            f"{hint}"
        )
    return to_hexmesh(rows.bricks(), " + ".join(files), "NLIST", input_files=files)
