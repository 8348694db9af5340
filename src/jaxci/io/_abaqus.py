"""Read Abaqus input decks (``.inp``): nodes, elements, node and element sets with their ids, and the deck's text.

`read_abaqus` reads ``*NODE``, ``*ELEMENT``, ``*NSET`` and ``*ELSET`` (with ``GENERATE``, set names as members,
``*NSET, ELSET=``), anywhere in the deck (inside ``*PART`` / ``*ASSEMBLY`` too), and follows ``*INCLUDE`` files.
Node numbers become `HexMesh.node_ids`, element numbers `CellBlock.ids`; each ``*ELEMENT`` keyword becomes one cell
block, and the element type names (``C3D8R``, ``C3D20H``, ...) are kept per block as the field data
``abaqus:element_types``. Every other keyword block (``*MATERIAL``, ``*SOLID SECTION``, ``*STEP``, ``*BOUNDARY``,
...) is not modelled; the whole deck text, with its ``*INCLUDE`` files inlined, is kept as the field data
``abaqus:deck``, and `jaxci.io._abaqus_write.write_abaqus` writes it back with only the node coordinates changed.

Element types: the 3-D continuum elements ``[A-Z]*C3D<n>[A-Z]*`` (``C3D8``, ``C3D8R``, ``C3D8I``, ``C3D8H``,
``C3D8RH``, ``DC3D8``, ...) with n = 4, 5, 6, 8 (tetra, pyramid, wedge, hexahedron; Abaqus numbers their nodes
as VTK does) and the quadratic n = 10, 15, 20 (tetra, wedge, hexahedron with `CellBlock.midside` in Abaqus's
order, which is `jaxci.cells.EDGES`'s), and the shells, membranes, surfaces, trusses and beams of
`SURFACE_TYPES`. Elements of any other type (``MASS``, ``SPRING2``, ``COH3D8``, ``SC8R``, ``C3D27``, ...) stay in
the deck text but are not part of the mesh (their nodes are kept, never moved), counted in `HexMesh.notes`.

A deck has no item counts to check; each line is checked strictly instead, and a `MeshReadError` names the file and
line of: a node or element id that is not a positive integer (or is beyond int64), a node id or element id defined
twice (with both lines), a coordinate that is not a finite number, an element with too few or too many nodes or
referencing a node no ``*NODE`` defines, a set member that does not exist, and the keywords jaxci cannot follow
(``*NGEN``, ``*NFILL``, ``*NCOPY``, ``*NMAP``, ``*ELGEN``, ``*ELCOPY``, ``*NODE, SYSTEM=C``, ``INPUT=`` on
``*NODE`` / ``*ELEMENT``). Node ids must be unique over the whole deck: a deck with several parts that each number
their nodes from 1 is refused (write the deck without parts, "flattened", to smooth it).
"""

from __future__ import annotations

import dataclasses
import os
import re
from pathlib import Path

import numpy as np

from ..errors import MeshReadError
from ..mesh import CellBlock, HexMesh
from ._deck import node_finder, parse_id, read_text, refuse_duplicates
from ._fields import parse_real
from ._paths import check_regular, resolve_beside

#: Abaqus shell, membrane, surface, truss and beam elements jaxci keeps as cells (not smoothed), with their cell type.
SURFACE_TYPES = {
    **{t: "quad" for t in ("S4", "S4R", "S4R5", "S4RS", "S4RSW", "S4T", "S4RT", "M3D4", "M3D4R", "SFM3D4",
                           "SFM3D4R", "R3D4", "CPS4", "CPS4R", "CPE4", "CPE4R", "CAX4", "CAX4R", "CAX4P")},
    **{t: "triangle" for t in ("S3", "S3R", "S3RS", "STRI3", "M3D3", "SFM3D3", "R3D3", "CPS3", "CPE3", "CAX3")},
    **{t: "quad8" for t in ("S8R", "S8R5", "M3D8", "M3D8R", "SFM3D8", "SFM3D8R", "CPS8", "CPS8R", "CPE8", "CPE8R")},
    "S9R5": "quad9",
    **{t: "triangle6" for t in ("STRI65", "M3D6", "SFM3D6", "CPS6", "CPE6")},
    **{t: "line" for t in ("T3D2", "T3D2H", "B31", "B31H", "T2D2", "B21")},
    **{t: "line3" for t in ("T3D3", "T3D3H", "B32", "B32H", "B22")},
}
#: ``C3D<n>``: the jaxci cell type and number of corner nodes of each 3-D continuum node count n.
SOLID_TYPES = {4: ("tetra", 4), 5: ("pyramid", 5), 6: ("wedge", 6), 8: ("hexahedron", 8), 10: ("tetra", 4),
               15: ("wedge", 6), 20: ("hexahedron", 8)}
_SOLID = re.compile(r"[A-Z]*C3D(\d+)[A-Z]*")
#: Keywords that generate or move nodes and elements, which jaxci would not see.
_GENERATORS = ("NGEN", "NFILL", "NCOPY", "NMAP", "ELGEN", "ELCOPY")
#: Keywords jaxci models (everything else is kept as text).
MODELLED = ("NODE", "ELEMENT", "NSET", "ELSET", "HEADING", "INCLUDE")
_MAX_INCLUDE_DEPTH = 20


def element_family(name: str) -> tuple[str, int, int] | None:
    """(jaxci cell type, corner nodes, all nodes) of an Abaqus element type name, or None for a type jaxci
    does not model."""
    name = name.upper()
    if name in SURFACE_TYPES:
        from ..mesh import NODES_PER_CELL

        n = NODES_PER_CELL[SURFACE_TYPES[name]]
        return SURFACE_TYPES[name], n, n
    m = _SOLID.fullmatch(name)
    if m and int(m.group(1)) in SOLID_TYPES:
        cell, corners = SOLID_TYPES[int(m.group(1))]
        return cell, corners, int(m.group(1))
    return None


# ---------------------------------------------------------------------------------------------------- the text
def split_line(line: str) -> tuple[str, str]:
    """A line and its line ending."""
    body = line.rstrip("\r\n")
    return body, line[len(body):]


def _keyword(text: str) -> tuple[str, dict[str, str | None]]:
    """Name (upper case, single spaces) and parameters (upper-case keys, values unquoted) of a keyword line."""
    parts = text.strip()[1:].split(",")
    name = " ".join(parts[0].split()).upper()
    params = {}
    for p in parts[1:]:
        if not p.strip():
            continue
        key, eq, value = p.partition("=")
        params[" ".join(key.split()).upper()] = value.strip().strip('"') if eq else None
    return name, params


def _is_keyword(body: str) -> bool:
    s = body.lstrip()
    return s.startswith("*") and not s.startswith("**")


def flatten(path: str, depth: int = 0) -> tuple[list[str], list[tuple[str, int]], list[str]]:
    """The lines of a deck with its ``*INCLUDE`` files inlined (line endings kept), where each came from, and the
    included files."""
    lines, origin, included = [], [], []
    text = read_text(path, "Abaqus deck", errors="surrogateescape")
    for lineno, line in enumerate(text.splitlines(keepends=True), 1):
        body, _ = split_line(line)
        if _is_keyword(body) and _keyword(body)[0] == "INCLUDE":
            name = _keyword(body)[1].get("INPUT")
            at = f"{path}, line {lineno}"
            if not name:
                raise MeshReadError(f"{at}: *INCLUDE without INPUT=")
            if depth >= _MAX_INCLUDE_DEPTH:
                raise MeshReadError(f"{at}: *INCLUDE nested more than {_MAX_INCLUDE_DEPTH} deep (a cycle?)")
            target = resolve_beside(name, path)
            if not os.path.lexists(target):
                raise MeshReadError(f"{at}: *INCLUDE file {name} not found (looked for {target})")
            check_regular(target, "Abaqus deck", shown=f"{at}: *INCLUDE file {name}")
            sub, sub_origin, sub_inc = flatten(str(target), depth + 1)
            if sub and not sub[-1].endswith(("\n", "\r")):
                sub[-1] += "\n"
            lines += sub
            origin += sub_origin
            included += [str(target), *sub_inc]
        else:
            lines.append(line)
            origin.append((path, lineno))
    return lines, origin, included


# ---------------------------------------------------------------------------------------------------- parsing
@dataclasses.dataclass
class _Block:
    """One ``*ELEMENT`` keyword of a modelled type."""

    name: str  # Abaqus element type, upper case
    cell: str
    corners: int
    n_nodes: int
    ids: list[int] = dataclasses.field(default_factory=list)
    nodes: list[list[int]] = dataclasses.field(default_factory=list)
    line: list[int] = dataclasses.field(default_factory=list)  # line index of each element


@dataclasses.dataclass(frozen=True)
class _Range:
    """A ``GENERATE`` line: ids `first`, `first` + `step`, ... up to `last`."""

    first: int
    last: int
    step: int

    @property
    def count(self) -> int:
        return (self.last - self.first) // self.step + 1

    def resolve(self, sorted_ids: np.ndarray) -> tuple[np.ndarray, int | None]:
        """The ids of the range that are among `sorted_ids` (sorted, unique), and the first id of the range that
        is not (None when all are): computed from the ids that exist, so a range of 10^12 ids costs what the
        mesh costs."""
        lo = np.searchsorted(sorted_ids, self.first, side="left")
        hi = np.searchsorted(sorted_ids, self.last, side="right")
        cand = sorted_ids[lo:hi]
        hit = cand[(cand - self.first) % self.step == 0]
        if len(hit) == self.count:
            return hit, None
        want = self.first + self.step * np.arange(len(hit), dtype=np.int64)
        k = int(np.argmax(hit != want)) if len(hit) and (hit != want).any() else len(hit)
        return hit, self.first + self.step * k


@dataclasses.dataclass
class _Set:
    name: str
    kind: str  # "node" | "element"
    entries: list = dataclasses.field(default_factory=list)  # (line index, ids or set name or ("elset", name))


class Deck:
    """A parsed deck: the flattened `lines`, the nodes (ids, coordinates, line index of each), the element blocks,
    the sets, and the keywords and element types it holds that jaxci does not model."""

    def __init__(self, lines: list[str], origin: list[tuple[str, int]], path: str) -> None:
        self.lines, self.origin, self.path = lines, origin, path
        self.node_ids: list[int] = []
        self.xyz: list[tuple[float, float, float]] = []
        self.node_line: list[int] = []
        self.node_part: list[str | None] = []
        self.blocks: list[_Block] = []
        self.sets: dict[str, _Set] = {}
        self.other_keywords: dict[str, int] = {}
        self.other_types: dict[str, int] = {}
        self.part: str | None = None
        self._parse()

    def where(self, i: int) -> str:
        f, n = self.origin[i]
        return f"{f}, line {n}"

    # ------------------------------------------------------------------ structure
    def _parse(self) -> None:
        i, n = 0, len(self.lines)
        while i < n:
            body, _ = split_line(self.lines[i])
            if not _is_keyword(body):
                i += 1  # data lines before the first keyword, comments, blank lines
                continue
            start, text = i, body
            while text.rstrip().endswith(",") and i + 1 < n and not _is_keyword(self.lines[i + 1]) \
                    and not self.lines[i + 1].lstrip().startswith("**"):
                i += 1  # a keyword line continued on the next line
                text = text.rstrip() + split_line(self.lines[i])[0]
            i += 1
            data = []
            while i < n and not _is_keyword(split_line(self.lines[i])[0]):
                s = self.lines[i].strip()
                if s and not s.startswith("**"):
                    data.append(i)
                i += 1
            self._keyword(start, *_keyword(text), data)

    def _keyword(self, start: int, name: str, params: dict, data: list[int]) -> None:
        at = self.where(start)
        if name == "PART":
            self.part = params.get("NAME") or "?"
        elif name == "END PART":
            self.part = None
        if name == "NODE":
            self._nodes(at, params, data)
        elif name == "ELEMENT":
            self._elements(at, params, data)
        elif name in ("NSET", "ELSET"):
            self._set(at, name, params, data)
        elif name in _GENERATORS:
            raise MeshReadError(f"{at}: *{name} generates or moves nodes or elements, which jaxci does not do; "
                                f"write the deck with every node and element listed")
        elif name not in MODELLED:
            self.other_keywords[name] = self.other_keywords.get(name, 0) + 1

    def _fields(self, i: int) -> list[str]:
        toks = [t.strip() for t in split_line(self.lines[i])[0].split(",")]
        while toks and not toks[-1]:
            toks.pop()
        return toks

    def _nodes(self, at: str, params: dict, data: list[int]) -> None:
        if (params.get("SYSTEM") or "R").upper() != "R":
            raise MeshReadError(f"{at}: *NODE, SYSTEM={params['SYSTEM']}: only rectangular (SYSTEM=R) node "
                                f"coordinates are supported")
        if params.get("INPUT"):
            raise MeshReadError(f"{at}: *NODE, INPUT={params['INPUT']}: node data in a separate file is not "
                                f"supported; *INCLUDE it instead")
        nset = self._new_set(params.get("NSET"), "node")
        ids = []
        for i in data:
            toks = self._fields(i)
            where = self.where(i)
            nid = parse_id(toks[0], where, "node id")
            if len(toks) > 7:
                raise MeshReadError(f"{where}: node {nid} has {len(toks)} fields; expected the id and at most 3 "
                                    f"coordinates and 3 normal components")
            xyz = [parse_real(t, where, f"coordinate {'xyz'[k]} of node {nid}") for k, t in
                   enumerate(toks[1:4])]
            self.node_ids.append(nid)
            self.xyz.append(tuple(xyz + [0.0] * (3 - len(xyz))))
            self.node_line.append(i)
            self.node_part.append(self.part)
            ids.append(nid)
        if nset is not None:
            nset.entries.append((data[0] if data else None, ids))

    def _elements(self, at: str, params: dict, data: list[int]) -> None:
        etype = (params.get("TYPE") or "").upper()
        if not etype:
            raise MeshReadError(f"{at}: *ELEMENT without TYPE=")
        if params.get("INPUT"):
            raise MeshReadError(f"{at}: *ELEMENT, INPUT={params['INPUT']}: element data in a separate file is not "
                                f"supported; *INCLUDE it instead")
        family = element_family(etype)
        elset = self._new_set(params.get("ELSET"), "element")
        if family is None:
            self.other_types[etype] = self.other_types.get(etype, 0) + len(data)
            return
        cell, corners, count = family
        blk = _Block(etype, cell, corners, count)
        acc: list[int] = []
        for i in data:
            where = self.where(i)
            toks = self._fields(i)
            if not acc:
                acc = [parse_id(toks[0], where, "element id")]
                blk.line.append(i)
                toks = toks[1:]
            acc += [parse_id(t, where, f"node id of element {acc[0]}") for t in toks]
            if len(acc) > count + 1:
                begun = f" (continued from line {self.origin[blk.line[-1]][1]})" if blk.line[-1] != i else ""
                raise MeshReadError(f"{where}: element {acc[0]}{begun} lists {len(acc) - 1} nodes; TYPE={etype} has "
                                    f"{count}")
            if len(acc) == count + 1:
                blk.ids.append(acc[0])
                blk.nodes.append(acc[1:])
                acc = []
        if acc:
            raise MeshReadError(f"{self.where(blk.line[-1])}: element {acc[0]} lists {len(acc) - 1} nodes; "
                                f"TYPE={etype} has {count} (truncated deck?)")
        if blk.ids:
            self.blocks.append(blk)
            if elset is not None:
                elset.entries.append((data[0], blk.ids))

    def _new_set(self, name: str | None, kind: str) -> _Set | None:
        if not name:
            return None
        key = (kind, name.upper())
        if key not in self.sets:
            self.sets[key] = _Set(name, kind)
        return self.sets[key]

    def _set(self, at: str, keyword: str, params: dict, data: list[int]) -> None:
        kind = "node" if keyword == "NSET" else "element"
        name = params.get(keyword)
        if not name:
            raise MeshReadError(f"{at}: *{keyword} without {keyword}=")
        s = self._new_set(name, kind)
        if kind == "node" and params.get("ELSET"):
            s.entries.append((None, ("elset", params["ELSET"])))
        generate = "GENERATE" in params
        for i in data:
            where = self.where(i)
            toks = self._fields(i)
            if generate:
                if len(toks) not in (2, 3):
                    raise MeshReadError(f"{where}: *{keyword}, GENERATE expects 'first, last[, step]', got "
                                        f"{len(toks)} fields")
                a, b = (parse_id(t, where, f"{kind} id") for t in toks[:2])
                step = parse_id(toks[2], where, "step") if len(toks) == 3 else 1
                if b < a:
                    raise MeshReadError(f"{where}: *{keyword}, GENERATE from {a} to {b}: last is below first")
                s.entries.append((i, _Range(a, b, step)))  # resolved against the ids that exist, never expanded
                continue
            for t in toks:
                if t and (t[0].isdigit() or t[0] in "+-"):
                    s.entries.append((i, [parse_id(t, where, f"{kind} id in {keyword} {name}")]))
                elif t:
                    s.entries.append((i, t.strip('"')))

    # ------------------------------------------------------------------ to arrays
    def mesh_parts(self) -> dict:
        """The arrays of a `HexMesh`: points, cell blocks, sets, ids (checks duplicates and references)."""
        if not self.node_ids:
            raise MeshReadError(f"{self.path}: no *NODE data found; not an Abaqus deck (or an empty one)")
        node_ids = np.array(self.node_ids, dtype=np.int64)
        def parts(i, j):
            if self.node_part[i] == self.node_part[j]:
                return ""
            return (f" (in parts {self.node_part[i]} and {self.node_part[j]}; jaxci needs node ids unique over the "
                    f"deck: write it without parts)")

        refuse_duplicates(node_ids, self.node_line, self.where, "node", parts)
        if not self.blocks:
            others = f" (only elements of types jaxci does not read: {', '.join(sorted(self.other_types))})" \
                if self.other_types else " (truncated deck, or not a volume mesh)"
            raise MeshReadError(f"{self.path}: {len(node_ids)} nodes but no elements{others}")
        elem_ids = np.concatenate([np.array(b.ids, dtype=np.int64) for b in self.blocks])
        elem_line = [i for b in self.blocks for i in b.line]
        refuse_duplicates(elem_ids, elem_line, self.where, "element")
        order = np.argsort(node_ids)
        sorted_ids = node_ids[order]
        find = node_finder(order, sorted_ids, self.where, "node", "which no *NODE defines")
        cells = []
        for b in self.blocks:
            conn = find(np.array(b.nodes, dtype=np.int64), b.line, b.ids, "element")
            if b.cell in ("hexahedron", "wedge", "tetra", "pyramid"):
                data, mid = conn[:, : b.corners], (conn[:, b.corners :] if b.n_nodes > b.corners else None)
            else:
                data, mid = conn, None
            cells.append(CellBlock(b.cell, data, np.array(b.ids, dtype=np.int64), mid))
        point_sets, cell_sets = self._resolve_sets(sorted_ids, order, elem_ids)
        return {"points": np.array(self.xyz, dtype=np.float64).reshape(-1, 3), "cells": tuple(cells),
                "node_ids": node_ids, "point_sets": point_sets, "cell_sets": cell_sets}

    def _resolve_sets(self, sorted_ids, order, elem_ids) -> tuple[dict, dict]:
        eorder = np.argsort(elem_ids)
        esorted = elem_ids[eorder]
        block_of = np.concatenate([np.full(len(b.ids), k) for k, b in enumerate(self.blocks)])
        row_of = np.concatenate([np.arange(len(b.ids)) for b in self.blocks])
        other = sum(self.other_types.values())
        members: dict[tuple[str, str], np.ndarray] = {}  # resolved ids per set
        for key, s in self.sets.items():
            ids = []
            for i, entry in s.entries:
                if isinstance(entry, list):
                    ids.append(np.array(entry, dtype=np.int64))
                    continue
                if isinstance(entry, _Range):
                    hit, gap = entry.resolve(sorted_ids if s.kind == "node" else esorted)
                    if gap is not None and (s.kind == "node" or not other):
                        word = "*NODE" if s.kind == "node" else "*ELEMENT"
                        raise MeshReadError(f"{self.where(i)}: {s.kind} set {s.name}, GENERATE from {entry.first} to "
                                            f"{entry.last} step {entry.step} ({entry.count} ids) lists {s.kind} {gap}, "
                                            f"which no {word} defines")
                    ids.append(hit)
                    continue
                if isinstance(entry, tuple):  # *NSET, ELSET=: the nodes of the elements of a set
                    eids = members.get(("element", entry[1].upper()))
                    if eids is None:
                        raise MeshReadError(f"{self.path}: *NSET {s.name}, ELSET={entry[1]}: no such element set")
                    rows = eorder[np.searchsorted(esorted, eids)].tolist()
                    nodes = [np.array(self.blocks[block_of[r]].nodes[row_of[r]], np.int64) for r in rows]
                    ids.append(np.unique(np.concatenate(nodes or [[]]).astype(np.int64)))
                    continue
                ref = members.get((s.kind, entry.upper()))
                if ref is None:
                    raise MeshReadError(f"{self.where(i)}: {s.kind} set {s.name} lists {entry!r}, which is neither "
                                        f"a {s.kind} id nor a {s.kind} set defined before it")
                ids.append(ref)
            members[key] = np.unique(np.concatenate(ids)) if ids else np.zeros(0, np.int64)
        point_sets, cell_sets = {}, {}
        for (kind, _), s in self.sets.items():
            ids = members[(kind, s.name.upper())]
            srt = sorted_ids if kind == "node" else esorted  # never empty: mesh_parts has checked
            pos = np.minimum(np.searchsorted(srt, ids), len(srt) - 1)
            missing = srt[pos] != ids
            if missing.any() and (kind == "node" or not other):
                line = next((i for i, e in s.entries if i is not None), None)
                at = self.where(line) if line is not None else self.path
                raise MeshReadError(f"{at}: {kind} set {s.name} lists {kind} {ids[missing][0]}, which no "
                                    f"{'*NODE' if kind == 'node' else '*ELEMENT'} defines")
            if kind == "node":
                point_sets[s.name] = np.sort(order[pos])
            else:
                rows = eorder[pos[~missing]]
                cell_sets[s.name] = [np.sort(row_of[rows[block_of[rows] == k]]) for k in range(len(self.blocks))]
        return point_sets, cell_sets


def parse_deck(text_lines: list[str], origin: list[tuple[str, int]], path: str) -> tuple[Deck, dict]:
    """Parse a flattened deck: the `Deck` and the keyword arguments of its `HexMesh` (without source and notes)."""
    deck = Deck(text_lines, origin, path)
    parts = deck.mesh_parts()
    parts["field_data"] = {"abaqus:deck": "".join(text_lines),
                           "abaqus:element_types": tuple(b.name for b in deck.blocks)}
    return deck, parts


def read_abaqus(path: str | os.PathLike) -> HexMesh:
    """Read an Abaqus input deck.

    **Arguments:** `path` the ``.inp`` file.

    **Returns:** a `HexMesh` with the deck's node ids, element ids, one cell block per ``*ELEMENT`` keyword of a
    type jaxci reads, the node and element sets, and as field data the element type names (``abaqus:element_types``)
    and the deck text (``abaqus:deck``, ``*INCLUDE`` files inlined). Raises `MeshReadError` naming the file and
    line of a malformed or duplicate node or element (module docstring).
    """
    path = os.fspath(path)
    lines, origin, included = flatten(path)
    deck, parts = parse_deck(lines, origin, path)
    notes = []
    if deck.other_types:
        listed = ", ".join(f"{n} {t}" for t, n in sorted(deck.other_types.items()))
        notes.append(f"elements of types jaxci does not read ({listed}) are kept in the deck but not smoothed; "
                     f"their nodes are never moved")
    if included:
        notes.append(f"{len(included)} *INCLUDE files read ({', '.join(Path(p).name for p in included[:4])}"
                     f"{', ...' if len(included) > 4 else ''}); a deck jaxci writes holds their lines in place of "
                     f"the *INCLUDE")
    return HexMesh(source=path, input_files=tuple(dict.fromkeys(included)), notes=tuple(notes), **parts)


def deck_extras(text: str) -> tuple[list[str], list[str]]:
    """The keywords (``*MATERIAL``, ...) and the element type names other than plain ``C3D8`` etc. that a deck's
    text holds: what a file written afresh from its mesh loses."""
    keywords, types = {}, {}
    for line in text.splitlines():
        if _is_keyword(line):
            name, params = _keyword(line)
            if name not in MODELLED and not name.startswith("END "):
                keywords[f"*{name}"] = None
            if name == "ELEMENT" and params.get("TYPE"):
                t = params["TYPE"].upper()
                if t not in DEFAULT_NAMES.values():
                    types[t] = None
    return list(keywords), list(types)


#: The Abaqus element type jaxci writes for a cell block with no type name of its own: by (cell type, quadratic).
DEFAULT_NAMES = {
    ("hexahedron", False): "C3D8", ("hexahedron", True): "C3D20", ("wedge", False): "C3D6", ("wedge", True): "C3D15",
    ("tetra", False): "C3D4", ("tetra", True): "C3D10", ("pyramid", False): "C3D5", ("quad", False): "S4",
    ("triangle", False): "S3", ("quad8", False): "S8R", ("quad9", False): "S9R5", ("triangle6", False): "STRI65",
    ("line", False): "T3D2", ("line3", False): "T3D3", ("hexahedron20", False): "C3D20",
    ("tetra10", False): "C3D10", ("wedge15", False): "C3D15",
}
