"""Read Nastran bulk data decks (``.bdf``, ``.nas``, and ``.dat`` when it holds Nastran cards).

`read_nastran` reads the bulk data section (after ``BEGIN BULK`` when the deck has one, up to ``ENDDATA``) in all
three card formats: small field (8-character fields), large field (``GRID*``: 16-character fields, continued on a
line starting with ``*``) and free field (fields separated by commas), with continuation lines (a line whose first
field is blank or starts with ``+``, ``*`` or ``,``), ``$`` comments, tabs (8-column stops) and ``INCLUDE 'file'``
statements (the included lines inlined, the files in `HexMesh.input_files`). Reals may use Nastran's short
exponents (``1.5-3``).

- ``GRID``: node id and coordinates, in the basic coordinate system only: a ``GRID`` (or ``GRDSET``) with a
  coordinate system ``CP`` other than blank or 0 is refused (`MeshReadError` naming the GRID), since its
  coordinates are not the node's position.
- ``CHEXA`` (8 nodes; up to 20 with midside nodes, any of them left blank), ``CPENTA`` (6 / 15), ``CTETRA``
  (4 / 10), ``CPYRAM`` (5 / 13): one cell block per card name and linear / quadratic, with the element ids as
  `CellBlock.ids`, the midside nodes as `CellBlock.midside` (PATRAN's edge order, `jaxci.io._patran`) and the
  property ids as the cell data ``nastran:pid``. ``CQUAD4``, ``CTRIA3``, ``CBAR``, ``CBEAM`` and ``CROD`` are kept
  as ``quad``, ``triangle`` and ``line`` cells (never smoothed).
- Every other card (materials, properties, loads, constraints, rigid elements, coordinate systems, ...) is not
  modelled; the deck text is kept as the field data ``nastran:deck`` and
  `jaxci.io._nastran_write.write_nastran` writes it back with only the GRID coordinates changed.

A `MeshReadError` names the file and line of: a GRID or element id that is not a positive integer or is defined
twice, a coordinate that is not a number, an element with a missing corner node or referencing a GRID the deck
does not define, a deck cut inside a card, and a deck without GRIDs (not Nastran).
"""

from __future__ import annotations

import dataclasses
import os
import re

import numpy as np

from ..errors import MeshReadError
from ..mesh import CellBlock, HexMesh
from ._ansys_apdl import read_apdl
from ._deck import checked_ids, parse_id
from ._fields import parse_real
from ._includes import flatten
from ._patran import split_solid

#: Element card -> (cell type, corner nodes, all nodes); the nodes follow the element and property ids.
ELEMENT_CARDS = {
    "CHEXA": ("hexahedron", 8, 20), "CPENTA": ("wedge", 6, 15), "CTETRA": ("tetra", 4, 10),
    "CPYRAM": ("pyramid", 5, 13), "CQUAD4": ("quad", 4, 4), "CTRIA3": ("triangle", 3, 3),
    "CBAR": ("line", 2, 2), "CBEAM": ("line", 2, 2), "CROD": ("line", 2, 2),
}
_INCLUDE = re.compile(r"\s*INCLUDE\s+'([^']+)'", re.IGNORECASE)
_BEGIN_BULK = re.compile(r"\s*BEGIN\s+(BULK|SUPER)", re.IGNORECASE)
_ENDDATA = re.compile(r"\s*ENDDATA", re.IGNORECASE)


def find_include(lines: list[str], i: int):
    m = _INCLUDE.match(lines[i])
    return (m.group(1), 1) if m else None


@dataclasses.dataclass
class Card:
    """One bulk data card: its name (upper case, without ``*``), data fields (text) and where each is: (line
    index, `jaxci.io._fields.replace_field` spec, width)."""

    name: str
    line: int
    fields: list[str] = dataclasses.field(default_factory=list)
    spots: list[tuple] = dataclasses.field(default_factory=list)


def _content(line: str) -> str:
    body = line.rstrip("\r\n")
    cut = body.find("$")
    return body if cut < 0 else body[:cut]


def is_continuation(line: str) -> bool:
    """Whether a bulk data line continues the card above it."""
    text = _content(line).expandtabs(8)
    if not text.strip():
        return False
    return text[0] in "+*," or not text[:8].strip()


def line_fields(line: str, first: bool, large_card: bool) -> tuple[str, bool, list[tuple[str, tuple, int]]]:
    """(name or continuation mark, large field, [(text, spot, width)] of the data fields) of one line."""
    text = _content(line)
    if "," in text:
        parts = text.split(",")
        mark = parts[0].strip()
        large = mark.endswith("*") or (not first and large_card and mark.startswith("*"))
        count = 4 if large else 8
        return mark, large, [(parts[k], ("free", k), 16 if large else 8) for k in range(1, min(len(parts),
                                                                                                count + 1))]
    text = text.expandtabs(8)
    mark = text[:8].strip()
    large = mark.endswith("*") if first else mark.startswith("*")
    width, count = (16, 4) if large else (8, 8)
    out = []
    for k in range(count):
        start = 8 + k * width
        out.append((text[start : start + width], ("fixed", start, width), width))
    return mark, large, out


def cards(lines: list[str], where) -> list[Card]:
    """The bulk data cards of a deck's lines (`where(i)` names line i in messages)."""
    start = 0
    for i, line in enumerate(lines):
        if _BEGIN_BULK.match(line):
            start = i + 1
            break
    out: list[Card] = []
    large = False
    for i in range(start, len(lines)):
        line = lines[i]
        if _ENDDATA.match(line):
            break
        text = _content(line)
        if not text.strip() or _INCLUDE.match(line):
            continue
        if is_continuation(line):
            if not out:
                raise MeshReadError(f"{where(i)}: a continuation line with no card before it")
            _, _, fields = line_fields(line, False, large)
            card = out[-1]
        else:
            mark, large, fields = line_fields(line, True, False)
            card = Card(mark.rstrip("*").upper(), i)
            out.append(card)
        for tok, spot, width in fields:
            card.fields.append(tok)
            card.spots.append((i, spot, width))
    return out


class Deck:
    """The nodes and elements of a deck's cards (`cards`), checked."""

    def __init__(self, lines: list[str], origin: list[tuple[str, int]], path: str) -> None:
        self.lines, self.origin, self.path = lines, origin, path
        self.node_ids, self.xyz, self.node_spots, self.node_line = [], [], [], []
        self.blocks: dict[tuple[str, bool], dict] = {}
        self.other: dict[str, int] = {}
        for card in cards(lines, self.where):
            if card.name == "GRID":
                self._grid(card)
            elif card.name in ELEMENT_CARDS:
                self._element(card)
            else:
                if card.name == "GRDSET" and len(card.fields) > 1 and card.fields[1].strip() not in ("", "0"):
                    raise MeshReadError(f"{self.where(card.line)}: GRDSET gives every GRID the coordinate system "
                                        f"CP={card.fields[1].strip()}; jaxci reads GRIDs in the basic system only")
                self.other[card.name] = self.other.get(card.name, 0) + 1

    def where(self, i: int) -> str:
        f, n = self.origin[i]
        return f"{f}, line {n}"

    def _grid(self, card: Card) -> None:
        at = self.where(card.line)
        f = card.fields + [""] * (5 - len(card.fields))
        nid = parse_id(f[0], at, "GRID id")
        if f[1].strip() not in ("", "0"):
            raise MeshReadError(f"{at}: GRID {nid} has its coordinates in coordinate system CP={f[1].strip()}; "
                                f"jaxci reads GRIDs in the basic system only (CP blank or 0)")
        xyz = [parse_real(f[2 + c], at, f"{'xyz'[c]} coordinate of GRID {nid}", nastran=True) for c in range(3)]
        if len(card.spots) < 5:
            raise MeshReadError(f"{at}: GRID {nid} is cut short (no field for its z coordinate)")
        self.node_ids.append(nid)
        self.xyz.append(xyz)
        self.node_spots.append([card.spots[2 + c] for c in range(3)])
        self.node_line.append(card.line)

    def _element(self, card: Card) -> None:
        at = self.where(card.line)
        cell, corners, full = ELEMENT_CARDS[card.name]
        f = [t.strip() for t in card.fields]
        eid = parse_id(f[0] if f else "", at, f"{card.name} id")
        pid = parse_id(f[1], at, f"property id of {card.name} {eid}") if len(f) > 1 and f[1] else 0
        raw = f[2 : 2 + full] + [""] * max(0, 2 + full - len(f))
        if not all(raw[:corners]):
            k = raw[:corners].index("")
            raise MeshReadError(f"{at}: {card.name} {eid} has no node G{k + 1} (it needs {corners} corner nodes; "
                                f"truncated deck?)")
        nodes = [parse_id(t, at, f"node G{k + 1} of {card.name} {eid}") if t else 0 for k, t in enumerate(raw)]
        quadratic = full > corners and any(nodes[corners:])
        key = (card.name, quadratic)
        blk = self.blocks.setdefault(key, {"ids": [], "pids": [], "nodes": [], "lines": []})
        blk["ids"].append(eid)
        blk["pids"].append(pid)
        blk["nodes"].append(nodes if quadratic else nodes[:corners])
        blk["lines"].append(card.line)

    def mesh_parts(self) -> dict:
        """Keyword arguments of the deck's `HexMesh` (without source, notes and field data)."""
        ids, find = checked_ids(self, "GRID", f"{self.path}: no GRID cards found; not a Nastran bulk data deck (or "
                                f"an empty one)", f"{self.path}: {{n}} GRIDs but no CHEXA, CPENTA, CTETRA or CPYRAM "
                                f"elements", "which the deck does not define")
        cells, pids = [], []
        for (name, _), b in self.blocks.items():
            cell, corners, _ = ELEMENT_CARDS[name]
            conn = find(b, name)
            data, mid = split_solid(conn, cell) if conn.shape[1] > corners else (conn, None)
            cells.append(CellBlock(cell, data, np.array(b["ids"], np.int64), mid))
            pids.append(np.array(b["pids"], np.int64))
        return {"points": np.array(self.xyz, np.float64).reshape(-1, 3), "cells": tuple(cells), "node_ids": ids,
                "cell_data": {"nastran:pid": pids}}


def parse_deck(lines: list[str], origin: list[tuple[str, int]], path: str) -> tuple[Deck, dict]:
    """A flattened deck's `Deck` and the keyword arguments of its `HexMesh` (without source and notes)."""
    deck = Deck(lines, origin, path)
    parts = deck.mesh_parts()
    parts["field_data"] = {"nastran:deck": "".join(lines)}
    return deck, parts


def read_nastran(path: str | os.PathLike) -> HexMesh:
    """Read a Nastran bulk data deck (module docstring).

    **Arguments:** `path` the deck (``.bdf``, ``.nas``, ``.dat``).

    **Returns:** a `HexMesh` with the GRID ids, one cell block per element card name (linear and quadratic apart),
    the property ids (cell data ``nastran:pid``) and the deck text (field data ``nastran:deck``). Raises
    `MeshReadError` naming the file and line of what is wrong.
    """
    path = os.fspath(path)
    if path.lower().endswith(".dat") and os.path.isfile(path) and not looks_like_nastran(path):
        if _looks_like_apdl(path):
            return read_apdl(path)  # an ANSYS .dat input file (Workbench's ds.dat)
        raise MeshReadError(f"{path}: a .dat file with neither Nastran cards (GRID, BEGIN BULK) nor ANSYS NBLOCK "
                            f"data; jaxci reads .dat as a Nastran bulk data deck or an ANSYS input file")
    lines, origin, included = flatten(path, find_include, "Nastran deck")
    deck, parts = parse_deck(lines, origin, path)
    notes = []
    if deck.other:
        listed = ", ".join(f"{n} {c}" for c, n in sorted(deck.other.items(), key=lambda kv: -kv[1])[:8])
        more = f", ... ({len(deck.other)} card names in all)" if len(deck.other) > 8 else ""
        notes.append(f"cards jaxci does not model are kept in the deck ({listed}{more}); nodes only they use are "
                     f"never moved")
    if included:
        notes.append(f"{len(included)} INCLUDE files read; a deck jaxci writes holds their lines in place of the "
                     f"INCLUDE")
    return HexMesh(source=path, notes=tuple(notes), input_files=tuple(included), **parts)


def _head(path) -> str:
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            return f.read(1 << 22)
    except OSError:
        return ""


def looks_like_nastran(path: str | os.PathLike) -> bool:
    """Whether a file (a ``.dat``) holds Nastran cards: a ``GRID`` or ``BEGIN BULK`` line in its first 4 MB."""
    return re.search(r"^(GRID[ *,\t]|BEGIN\s+BULK|CHEXA[ *,\t])", _head(path), re.IGNORECASE | re.MULTILINE) is not None


def _looks_like_apdl(path) -> bool:
    return re.search(r"^\s*NBLOCK\s*,", _head(path), re.IGNORECASE | re.MULTILINE) is not None
