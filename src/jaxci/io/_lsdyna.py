"""Read LS-DYNA keyword files (``.k``, ``.key``, ``.dyn``): ``*NODE``, ``*ELEMENT_SOLID`` and ``*INCLUDE``.

- ``*NODE``: node id and coordinates in fixed columns (8, 16, 16, 16; ``*NODE %`` or ``*KEYWORD I10=Y``: 10, 16,
  16, 16; ``*NODE +`` or ``*KEYWORD LONG=Y``: 20 each) or in free format (fields separated by commas).
- ``*ELEMENT_SOLID``: element id, part id and 8 nodes on one line, or the id and part on one line and the nodes on
  the next; bricks, and the degenerate forms LS-DYNA writes for other solids: a tetrahedron ``N1 N2 N3 N4 N4 N4 N4
  N4``, a pyramid ``N1 .. N5 N5 N5 N5`` and a wedge (pentahedron) ``N1 N2 N3 N4 N5 N5 N6 N6``, read as ``tetra``,
  ``pyramid`` and ``wedge`` cells. One cell block per cell type, element ids as `CellBlock.ids`, part ids as the
  cell data ``lsdyna:pid``.
- ``*INCLUDE``: the included file's lines are inlined (its own ``*KEYWORD`` and ``*END`` lines left out, since an
  ``*END`` would end the deck there), and the file is listed in `HexMesh.input_files` (never written over).

Every other keyword (``*PART``, ``*MAT_*``, ``*SECTION_*``, ``*ELEMENT_SHELL``, ``*BOUNDARY_*``, ``*SET_*``, ...)
is not modelled; nodes only such keywords use are never moved. The deck text is kept as the field data
``lsdyna:deck`` and `jaxci.io._lsdyna_write.write_lsdyna` writes it back with only the ``*NODE`` coordinates
changed. Keywords that would change what jaxci reads are refused with a `MeshReadError` naming file and line
(``*ELEMENT_SOLID_ORTHO`` and the other ``*ELEMENT_SOLID_`` forms, ``*INCLUDE_TRANSFORM`` and the other
``*INCLUDE_`` forms, ``*NODE_TRANSFORM``), and so are: a node or element id that is not a positive integer or
is defined twice, a coordinate that is not a number, an element referencing a node no ``*NODE`` defines, an element
whose repeated nodes are none of the forms above, a deck cut inside an element, and a deck without ``*NODE``.
"""

from __future__ import annotations

import os
import re

import numpy as np

from ..errors import MeshReadError
from ..mesh import CellBlock, HexMesh
from ._deck import checked_ids, parse_id
from ._fields import parse_real
from ._includes import flatten

#: Column widths of a ``*NODE`` line (id, x, y, z) and of an ``*ELEMENT_SOLID`` line's fields, per format.
NODE_WIDTHS = {"standard": (8, 16, 16, 16), "i10": (10, 16, 16, 16), "long": (20, 20, 20, 20)}
ELEMENT_WIDTH = {"standard": 8, "i10": 10, "long": 20}
#: Positions (among the 8 listed nodes) of the nodes of each degenerate form, in jaxci's (VTK) node order.
DEGENERATE = {"tetra": [0, 1, 2, 3], "pyramid": [0, 1, 2, 3, 4], "wedge": [1, 0, 4, 2, 3, 6]}
_KEYWORD = re.compile(r"\*\s*([A-Za-z0-9_]+)\s*([%+-])?")


def _is_keyword(line: str) -> bool:
    return line.startswith("*")


def _is_comment(line: str) -> bool:
    return line.startswith("$") or not line.strip()


def keyword(line: str) -> tuple[str, str | None]:
    """Name (upper case) and format sign (``%``, ``+``, ``-`` or None) of a keyword line."""
    m = _KEYWORD.match(line)
    return (m.group(1).upper(), m.group(2)) if m else ("", None)


def find_include(lines: list[str], i: int):
    if not _is_keyword(lines[i]) or keyword(lines[i])[0] != "INCLUDE":
        return None
    j = i + 1
    while j < len(lines) and _is_comment(lines[j]):
        j += 1
    if j >= len(lines) or _is_keyword(lines[j]):
        raise MeshReadError(f"line {i + 1}: *INCLUDE without a file name on the next line")
    return lines[j].strip(), j - i + 1


def _row(line: str, widths, free_width: int) -> list[tuple[str, tuple, int]]:
    """(text, `jaxci.io._fields.replace_field` spot, width) of each field of a data line."""
    body = line.rstrip("\r\n")
    if "," in body:
        return [(t, ("free", k), free_width) for k, t in enumerate(body.split(","))]
    out, start = [], 0
    for w in widths:
        out.append((body[start : start + w], ("fixed", start, w), w))
        start += w
    return out


class Deck:
    """The nodes and solid elements of a flattened keyword deck, checked."""

    def __init__(self, lines: list[str], origin: list[tuple[str, int]], path: str) -> None:
        self.lines, self.origin, self.path = lines, origin, path
        self.node_ids, self.xyz, self.node_spots, self.node_line = [], [], [], []
        self.blocks: dict[str, dict] = {}
        self.other: dict[str, int] = {}
        self.default = "standard"
        i, n = 0, len(lines)
        while i < n:
            if not _is_keyword(lines[i]):
                i += 1
                continue
            name, sign = keyword(lines[i])
            start = i
            i += 1
            data = []
            while i < n and not _is_keyword(lines[i]):
                if not _is_comment(lines[i]):
                    data.append(i)
                i += 1
            self._keyword(start, name, sign, data)

    def where(self, i: int) -> str:
        f, n = self.origin[i]
        return f"{f}, line {n}"

    def _format(self, sign: str | None) -> str:
        return {"%": "i10", "+": "long", "-": "standard"}.get(sign or "", self.default)

    def _keyword(self, start: int, name: str, sign: str | None, data: list[int]) -> None:
        at = self.where(start)
        text = self.lines[start].upper()
        if name == "KEYWORD":
            if re.search(r"LONG\s*=\s*Y", text):
                self.default = "long"
            elif re.search(r"I10\s*=\s*Y", text):
                self.default = "i10"
        elif name == "NODE":
            self._nodes(self._format(sign), data)
        elif name == "ELEMENT_SOLID":
            self._solids(self._format(sign), data)
        elif name.startswith(("ELEMENT_SOLID_", "INCLUDE_", "NODE_TRANSFORM")):
            raise MeshReadError(f"{at}: *{name}: jaxci reads *NODE, *ELEMENT_SOLID and *INCLUDE, not *{name} (it "
                                f"would change the nodes or solids jaxci reads); write the deck without it")
        elif name not in ("", "END", "TITLE", "COMMENT"):
            self.other[name] = self.other.get(name, 0) + 1

    def _nodes(self, fmt: str, data: list[int]) -> None:
        widths = NODE_WIDTHS[fmt]
        for i in data:
            at = self.where(i)
            row = _row(self.lines[i], widths, widths[1])
            if len(row) < 2 or not row[0][0].strip():
                raise MeshReadError(f"{at}: a *NODE line without a node id")
            nid = parse_id(row[0][0], at, "node id")
            row += [("", None, 0)] * (4 - len(row))
            xyz = [parse_real(row[1 + c][0], at, f"{'xyz'[c]} coordinate of node {nid}") for c in range(3)]
            if any(spot is None for _, spot, _ in row[1:4]):
                raise MeshReadError(f"{at}: node {nid} has fewer than 3 coordinates (free format)")
            self.node_ids.append(nid)
            self.xyz.append(xyz)
            self.node_spots.append([(i, spot, w) for _, spot, w in row[1:4]])
            self.node_line.append(i)

    def _solids(self, fmt: str, data: list[int]) -> None:
        w = ELEMENT_WIDTH[fmt]
        k = 0
        while k < len(data):
            i = data[k]
            at = self.where(i)
            fields = [t.strip() for t, _, _ in _row(self.lines[i], [w] * 10, w)]
            while fields and not fields[-1]:
                fields.pop()
            if not fields:
                raise MeshReadError(f"{at}: an *ELEMENT_SOLID line without an element id")
            eid = parse_id(fields[0], at, "element id")
            pid = parse_id(fields[1], at, f"part id of element {eid}") if len(fields) > 1 and fields[1] else 0
            nodes = fields[2:]
            k += 1
            if not nodes:  # the two-line form: the nodes on the next line
                if k >= len(data):
                    raise MeshReadError(f"{at}: element {eid} has no nodes (truncated deck?)")
                nodes = [t.strip() for t, _, _ in _row(self.lines[data[k]], [w] * 10, w)]
                at = self.where(data[k])
                k += 1
            nodes = [parse_id(t, at, f"node N{c + 1} of element {eid}") if t and t != "0" else 0
                     for c, t in enumerate(nodes[:8])]
            cell, corners = self._form(nodes + [0] * (8 - len(nodes)), eid, at)
            blk = self.blocks.setdefault(cell, {"ids": [], "pids": [], "nodes": [], "lines": []})
            blk["ids"].append(eid)
            blk["pids"].append(pid)
            blk["nodes"].append(corners)
            blk["lines"].append(i)

    @staticmethod
    def _form(n: list[int], eid: int, at: str) -> tuple[str, list[int]]:
        """(cell type, nodes in jaxci's order) of the 8 listed nodes of a solid (0: blank)."""
        if 0 in n[:4]:
            raise MeshReadError(f"{at}: element {eid} lists {sum(v != 0 for v in n)} nodes; a solid needs at least "
                                f"4 (truncated deck?)")
        if not any(n[4:]):  # only N1..N4 listed: a tetrahedron
            n = n[:4] + [n[3]] * 4
        elif 0 in n[4:]:
            raise MeshReadError(f"{at}: element {eid} lists {sum(v != 0 for v in n)} nodes; a solid lists 8 "
                                f"(truncated deck?)")
        distinct = len(set(n))
        if distinct == 8:
            return "hexahedron", n
        if distinct == 4 and n[3] == n[4] == n[5] == n[6] == n[7]:
            return "tetra", [n[p] for p in DEGENERATE["tetra"]]
        if distinct == 5 and n[4] == n[5] == n[6] == n[7]:
            return "pyramid", [n[p] for p in DEGENERATE["pyramid"]]
        if distinct == 6 and n[4] == n[5] and n[6] == n[7]:
            return "wedge", [n[p] for p in DEGENERATE["wedge"]]
        raise MeshReadError(f"{at}: element {eid} repeats nodes ({' '.join(map(str, n))}) in a form jaxci does not "
                            f"read; it reads bricks and the degenerate tetrahedron (N4 x5), pyramid (N5 x4) and "
                            f"wedge (N5 N5 N6 N6)")

    def mesh_parts(self) -> dict:
        """Keyword arguments of the deck's `HexMesh` (without source, notes and field data)."""
        ids, find = checked_ids(self, "node", f"{self.path}: no *NODE data found; not an LS-DYNA keyword deck (or an "
                                f"empty one)", f"{self.path}: {{n}} nodes but no *ELEMENT_SOLID elements",
                                "which no *NODE defines")
        cells = tuple(CellBlock(cell, find(b, "element"), np.array(b["ids"], np.int64)) for cell, b in
                      self.blocks.items())
        return {"points": np.array(self.xyz, np.float64).reshape(-1, 3), "cells": cells, "node_ids": ids,
                "cell_data": {"lsdyna:pid": [np.array(b["pids"], np.int64) for b in self.blocks.values()]}}


def parse_deck(lines: list[str], origin: list[tuple[str, int]], path: str) -> tuple[Deck, dict]:
    """A flattened deck's `Deck` and the keyword arguments of its `HexMesh` (without source and notes)."""
    deck = Deck(lines, origin, path)
    parts = deck.mesh_parts()
    parts["field_data"] = {"lsdyna:deck": "".join(lines)}
    return deck, parts


def read_lsdyna(path: str | os.PathLike) -> HexMesh:
    """Read an LS-DYNA keyword deck (module docstring).

    **Arguments:** `path` the deck (``.k``, ``.key``, ``.dyn``).

    **Returns:** a `HexMesh` with the node ids, one cell block per solid type, the part ids (cell data
    ``lsdyna:pid``), the deck text with its includes inlined (field data ``lsdyna:deck``) and the included files
    (`HexMesh.input_files`). Raises `MeshReadError` naming the file and line of what is wrong.
    """
    path = os.fspath(path)
    try:
        lines, origin, included = flatten(path, find_include, "LS-DYNA keyword deck")
    except MeshReadError as exc:
        msg = str(exc)
        raise MeshReadError(msg if msg.startswith(path) else f"{path}, {msg}") from None
    keep = [k for k, (f, _) in enumerate(origin) if f == path or keyword(lines[k])[0] not in ("KEYWORD", "END")]
    lines, origin = [lines[k] for k in keep], [origin[k] for k in keep]
    deck, parts = parse_deck(lines, origin, path)
    notes = []
    if deck.other:
        listed = ", ".join(f"*{c}" for c in sorted(deck.other)[:8])
        more = f", ... ({len(deck.other)} in all)" if len(deck.other) > 8 else ""
        notes.append(f"keywords jaxci does not model are kept in the deck ({listed}{more}); nodes only they use are "
                     f"never moved")
    if included:
        notes.append(f"{len(included)} *INCLUDE files read; a deck jaxci writes holds their lines in place of the "
                     f"*INCLUDE")
    return HexMesh(source=path, notes=tuple(notes), input_files=tuple(included), **parts)
