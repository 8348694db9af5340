"""What the solver-deck formats (Abaqus ``.inp``, ANSYS ``.cdb`` / APDL) share: ids, and writing a deck back in place.

A mesh read from an Abaqus deck or an ANSYS archive carries the file's text as field data (``abaqus:deck``,
``ansys:deck``): materials, sections, loads, steps and every other line jaxci does not model. When such a mesh is
written to the same kind of file and differs from the deck only in its node coordinates (`model_difference`), the
writer rewrites the coordinates of the node lines and keeps every other line byte for byte. Otherwise it writes the
mesh afresh and `jaxci.io._losses.deck_losses` says, in a `LossyWriteWarning` issued before writing, what of
the deck is lost.
"""

from __future__ import annotations

import os
import warnings

import numpy as np

from ..errors import MeshReadError, MeshWriteError
from ..mesh import HexMesh
from ._paths import open_text, os_reason

#: Largest id jaxci holds (numpy int64). Ids are positive: 1 .. MAX_ID.
MAX_ID = 2**63 - 1


def parse_id(token: str, where: str, what: str) -> int:
    """A positive integer id (node or element number) from a text field, or a `MeshReadError` at `where`."""
    tok = token.strip()
    try:
        value = int(tok)
    except ValueError:
        try:
            f = float(tok.replace("D", "E").replace("d", "e"))
        except ValueError:
            f = None
        if f is None or not np.isfinite(f) or f != int(f):
            raise MeshReadError(f"{where}: {what} {tok!r} is not an integer") from None
        value = int(f)
    if value < 1:
        raise MeshReadError(f"{where}: {what} {value} is not positive (ids start at 1)")
    if value > MAX_ID:
        raise MeshReadError(f"{where}: {what} {value} is too large (jaxci reads ids up to {MAX_ID})")
    return value


def read_text(path: str | os.PathLike, what: str, errors: str = "strict") -> str:
    """The text of a file with its line endings, or a `MeshReadError` naming the file.

    `errors` is the decoding error handler: ``"strict"`` refuses undecodable bytes, ``"surrogateescape"`` keeps any
    bytes (undecodable ones as surrogates). Anything but a regular file (a folder, a FIFO, a device) is refused
    before it is read (`jaxci.io._paths.open_text`).
    """
    try:
        with open_text(path, what, errors) as f:
            return f.read()
    except UnicodeDecodeError as exc:
        raise MeshReadError(f"{path}: not a text {what} (undecodable byte at offset {exc.start})") from None
    except OSError as exc:
        raise MeshReadError(f"{path}: cannot read ({os_reason(exc)})") from None


def is_number(tok: str) -> bool:
    """Whether a token reads as a float."""
    try:
        float(tok)
    except ValueError:
        return False
    return True


def first_duplicate(ids: np.ndarray) -> tuple[int, int] | None:
    """Positions (first, second) of the first repeated value of `ids` in file order, or None."""
    ids = np.asarray(ids)
    order = np.argsort(ids, kind="stable")
    same = np.flatnonzero(ids[order][1:] == ids[order][:-1])
    if len(same) == 0:
        return None
    pairs = np.stack([order[same], order[same + 1]], axis=1)
    return tuple(int(p) for p in pairs[np.argmin(pairs[:, 1])])


def element_ids(ids: list, counts: list[int]) -> list[np.ndarray]:
    """The element ids of each block written: its own (``ids[k]``), or for a block without (None) its ``counts[k]``
    numbers after the largest id given, continuing from block to block."""
    next_id = int(max((i.max() for i in ids if i is not None and len(i)), default=0)) + 1
    out = []
    for i, n in zip(ids, counts, strict=True):
        if i is None:
            i = np.arange(next_id, next_id + n)
            next_id += n
        out.append(i)
    return out


def refuse_bad_ids(path: str, arrays, fmt: str, maximum: int | None = None, held: str = "") -> None:
    """`MeshWriteError` at the first id of ``(ids, what)`` in `arrays` (``what``: ``"node"``, ``"element"``, ...)
    that is used twice (`fmt` names the format), is not positive, or, with a `maximum`, lies outside ``1..maximum``
    (`held`: what cannot hold it, e.g. ``"of the 8-character fields"``)."""
    for ids, what in arrays:
        if (dup := first_duplicate(ids)) is not None:
            raise MeshWriteError(f"{path}: {what} id {ids[dup[1]]} is used twice; {fmt} ids must be unique")
        if maximum is None and len(ids) and ids.min() < 1:
            raise MeshWriteError(f"{path}: {what} id {ids.min()} is not positive; {fmt} ids start at 1")
        if maximum is not None and len(ids) and (ids.min() < 1 or ids.max() > maximum):
            bad = ids.min() if ids.min() < 1 else ids.max()
            raise MeshWriteError(f"{path}: {what} id {bad} is out of the range 1..{maximum} {held}")


def refuse_duplicates(ids, lines, where, what: str, more=None) -> None:
    """`MeshReadError` at the second definition of the first id of `ids` (file order) defined twice: ``where(
    line)`` names a line of `lines` (one per id), `what` the entity (``"node"``, ``"GRID"``, ``"element"``),
    ``more(i, j)`` may add a sentence about the first and second positions."""
    if (dup := first_duplicate(ids)) is not None:
        i, j = dup
        extra = more(i, j) if more is not None else ""
        raise MeshReadError(f"{where(lines[j])}: {what} {ids[j]} is defined twice (first at {where(lines[i])})"
                            f"{extra}")


def node_finder(order: np.ndarray, srt: np.ndarray, where, node: str, undefined: str):
    """``find(raw, lines, eids, label)``: the positions among the node ids (unique; `order` sorts them into `srt`)
    of the node ids `raw` of an element block (rows; an id 0, a blank field, is no node: -1), or a `MeshReadError`
    at the first element that references an undefined one: ``where(lines[r])``, ``{label} {eids[r]} references
    {node} ID, {undefined}`` and how many elements do."""

    def find(raw: np.ndarray, lines, eids, label: str) -> np.ndarray:
        pos = np.minimum(np.searchsorted(srt, raw), len(srt) - 1)
        missing = (srt[pos] != raw) & (raw != 0)
        if missing.any():
            r, c = (int(v) for v in np.argwhere(missing)[0])
            raise MeshReadError(f"{where(lines[r])}: {label} {eids[r]} references {node} {raw[r, c]}, {undefined} "
                                f"({int(missing.any(axis=1).sum())} such elements)")
        return np.where(raw == 0, -1, order[pos])

    return find


def checked_ids(deck, node: str, no_nodes: str, no_elements: str, undefined: str):
    """The node ids of a parsed card deck (LS-DYNA, Nastran: `deck` has ``node_ids``, ``node_line``, ``where``
    and ``blocks`` of element ``ids`` and ``lines``), checked: a `MeshReadError` `no_nodes` where it has no node,
    `no_elements` (``{n}``: the node count) where it has no element, and at a node id (`node`: the format's word)
    or an element id defined twice. Returns ``(ids, find)``: the ids ``(n,)`` and ``find(block, label)``, the
    positions of the node ids of a block (`node_finder`, with `undefined`)."""
    if not deck.node_ids:
        raise MeshReadError(no_nodes)
    ids = np.array(deck.node_ids, np.int64)
    refuse_duplicates(ids, deck.node_line, deck.where, node)
    if not deck.blocks:
        raise MeshReadError(no_elements.format(n=len(ids)))
    blocks = deck.blocks.values()
    refuse_duplicates(np.concatenate([np.array(b["ids"], np.int64) for b in blocks]),
                      [i for b in blocks for i in b["lines"]], deck.where, "element")
    order = np.argsort(ids)
    find = node_finder(order, ids[order], deck.where, node, undefined)
    return ids, lambda b, label: find(np.array(b["nodes"], np.int64), b["lines"], b["ids"], label)


def _same_array(a, b) -> bool:
    if a is None or b is None:
        return a is None and b is None
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and bool(np.array_equal(a, b))


def _same_sets(a: dict, b: dict, per_block: bool) -> bool:
    if set(a) != set(b):
        return False
    for name in a:
        x, y = (a[name], b[name]) if per_block else ([a[name]], [b[name]])
        if len(x) != len(y):
            return False
        for u, v in zip(x, y, strict=True):
            u = np.unique(np.asarray(u if u is not None else [], np.int64))
            v = np.unique(np.asarray(v if v is not None else [], np.int64))
            if not np.array_equal(u, v):
                return False
    return True


def reread_deck(mesh: HexMesh, text: str, parse_deck):
    """The source deck `text` of `mesh` read again by its format's ``parse_deck`` (warnings silenced: they were
    given when it was first read), for an in-place write: ``(lines, deck, reference HexMesh)``."""
    lines = text.splitlines(keepends=True)
    label = f"the deck of {mesh.source or 'the mesh'}"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        deck, parts = parse_deck(lines, [(label, k + 1) for k in range(len(lines))], label)
        ref = HexMesh(**parts)
    return lines, deck, ref


def model_difference(mesh: HexMesh, deck: HexMesh, cell_data=(), point_data=(), field_data=()) -> str | None:
    """None when `mesh` is `deck` with other node coordinates; else what differs, for a message.

    **Arguments:** `mesh` the mesh to write; `deck` the mesh its source deck holds (read again); `cell_data`,
    `point_data`, `field_data` the names of the data the deck format stores, which must agree too.
    """
    if mesh.n_nodes != deck.n_nodes or not _same_array(mesh.node_ids, deck.node_ids):
        return "its nodes or node ids differ from the deck's"
    if mesh.hex_mirrored != deck.hex_mirrored or len(mesh.cells) != len(deck.cells):
        return "its cell blocks differ from the deck's"
    for a, b in zip(mesh.cells, deck.cells, strict=True):
        if a.type != b.type or not all(_same_array(x, y) for x, y in
                                       ((a.data, b.data), (a.ids, b.ids), (a.midside, b.midside))):
            return "its cells differ from the deck's"
    if not _same_sets(dict(mesh.point_sets), dict(deck.point_sets), False) or not _same_sets(
        dict(mesh.cell_sets), dict(deck.cell_sets), True
    ):
        return "its node or element sets differ from the deck's"
    for name in cell_data:
        x, y = mesh.cell_data.get(name), deck.cell_data.get(name)
        if (x is None) != (y is None) or (x is not None and not all(
                _same_array(u, v) for u, v in zip(x, y, strict=True))):
            return f"its cell data {name!r} differ from the deck's"
    for name in point_data:
        if not _same_array(mesh.point_data.get(name), deck.point_data.get(name)):
            return f"its point data {name!r} differ from the deck's"
    for name in field_data:
        x, y = mesh.field_data.get(name), deck.field_data.get(name)
        if (x is None) != (y is None) or (x is not None and not np.array_equal(np.asarray(x), np.asarray(y))):
            return f"its {name!r} differ from the deck's"
    return None
