"""Trust no header, Gmsh: the counts a Gmsh 2.2 or 4.1 file (ASCII or binary) announces must match what it holds.

meshio reads a Gmsh file whose $Elements header disagrees with its element lines without complaint. `check_gmsh`
runs before meshio on every Gmsh file `jaxci.io._meshio.read_meshio` reads (as `jaxci.io._counts` checks the VTK
formats) and raises a `MeshReadError` naming the file and what is missing or wrong: the $Nodes and $Elements
sections are walked entity block by entity block; every block must hold the nodes and elements its header
announces, the totals must match the section headers, the section must end where its $End line is, node and element
tags must be positive and unique, every node an element lists must be a node tag, and the largest node tag must be
small enough for meshio's lookup table (`TABLE_ENTRIES`).
"""

from __future__ import annotations

import re
from pathlib import Path

import meshio
import numpy as np

from ..errors import MeshReadError


class _Cursor:
    """Reads the numbers of one section: its whitespace-separated tokens (ASCII) or native binary values."""

    def __init__(self, data: bytes, pos: int, ascii_: bool, size_t: np.dtype, where: str, section: str) -> None:
        self.data, self.pos, self.ascii, self.size_t = data, pos, ascii_, size_t
        self.where, self.section = where, section
        if ascii_:
            stop = data.find(b"$End" + section.encode(), pos)
            if stop < 0:
                self.fail(f"no $End{section} (the file ends inside the section)")
            self.tokens, self.i = data[pos:stop].split(), 0

    def fail(self, what: str):
        raise MeshReadError(f"{self.where}: corrupt or truncated Gmsh file: ${self.section}: {what}")

    def ints(self, n: int, dtype) -> np.ndarray:
        """`n` integers (`dtype` their binary type: int32 or size_t)."""
        if self.ascii:
            if self.i + n > len(self.tokens):
                self.fail("fewer values than its headers announce")
            try:
                out = np.array(self.tokens[self.i : self.i + n]).astype(np.int64)
            except (ValueError, OverflowError):
                self.fail(f"value {self.i + 1} is not an integer of at most 64 bits")
            self.i += n
            return out
        dtype = np.dtype(dtype)
        end = self.pos + n * dtype.itemsize
        if end > len(self.data):
            self.fail("the file ends before the values its headers announce")
        out = np.frombuffer(self.data, dtype, n, self.pos).astype(np.int64)
        self.pos = end
        return out

    def skip(self, n: int, itemsize: int) -> None:
        """Skip `n` values of `itemsize` bytes each (in binary)."""
        if self.ascii:
            self.i += n
            if self.i > len(self.tokens):
                self.fail("fewer values than its headers announce")
        else:
            self.pos += n * itemsize
            if self.pos > len(self.data):
                self.fail("the file ends before the values its headers announce")

    def end(self) -> None:
        if self.ascii:
            if self.i != len(self.tokens):
                self.fail(f"{len(self.tokens) - self.i} values more than its headers announce")
            return
        m = re.compile(rb"\s*(\$\S*)").match(self.data, self.pos)
        if m is None or m.group(1) != b"$End" + self.section.encode():
            self.fail(f"more or other data than its headers announce (no $End{self.section} where they end)")


def _nodes_per_type(t: int, c: _Cursor) -> int:
    try:
        return meshio._common.num_nodes_per_cell[meshio.gmsh.common._gmsh_to_meshio_type[int(t)]]
    except KeyError:
        c.fail(f"unknown element type {int(t)}")


def _check_tags(tags: np.ndarray, where: str, what: str) -> None:
    section = "$Nodes" if what == "node" else "$Elements"
    if len(tags) and tags.min() < 1:
        raise MeshReadError(f"{where}: {what} tag {int(tags.min())} in {section} is not positive (Gmsh tags start "
                            f"at 1)")
    order = np.argsort(tags, kind="stable")
    same = np.flatnonzero(tags[order][1:] == tags[order][:-1])
    if len(same):
        k = int(order[same[0] + 1])
        raise MeshReadError(f"{where}: {what} tag {int(tags[k])} is defined twice in {section} ({what} "
                            f"{int(order[same[0]])} and {what} {k} in file order)")


#: Node tags meshio may index with a table of max tag + 1 entries: up to this many, or 16 per node of the file.
TABLE_ENTRIES = 1 << 24


def _check_table(tags: np.ndarray, where: str, itemsize: int) -> None:
    """meshio looks node tags up in a table as long as the largest tag (int32 entries for 2.2, int64 for 4.1): a
    sparse tag of 10^9 asks for gigabytes, 2^63 - 1 for more than exists. Refused with what it would cost."""
    if not len(tags):
        return
    top = int(tags.max())
    if top + 1 <= max(TABLE_ENTRIES, 16 * len(tags)):
        return
    size = (top + 1) * itemsize
    cost = f"{size / 2**30:.3g} GiB" if size < 2**70 else f"about 2^{size.bit_length() - 1} bytes"
    raise MeshReadError(f"{where}: node tag {top} is far beyond the {len(tags)} nodes of $Nodes: meshio, which reads "
                        f"Gmsh files for jaxci, looks tags up in a table as long as the largest tag ({cost}); "
                        f"renumber the nodes with consecutive tags from 1")


def check_gmsh(path: Path) -> None:
    """Gmsh 2.2 / 4.1: walk $Nodes and $Elements (module docstring). Files of other versions are left to meshio."""
    data = path.read_bytes()
    fmt = re.search(rb"\$MeshFormat\s+(\d+\.\d+)\s+(\d+)\s+(\d+)", data[:1024])
    if fmt is None or fmt.group(1) not in (b"2.2", b"4.1"):
        return
    v4, ascii_ = fmt.group(1) == b"4.1", fmt.group(2) == b"0"
    size_t = np.dtype(f"u{int(fmt.group(3))}")
    where = str(path)
    node_tags = None
    for name in ("Nodes", "Elements"):
        start = re.search(rb"(?m)^\$" + name.encode() + rb"\s*?\n", data)
        if start is None:
            if name == "Elements":
                raise MeshReadError(f"{where}: corrupt or truncated Gmsh file: no $Elements section")
            continue
        c = _Cursor(data, start.end(), ascii_, size_t, where, name)
        if ascii_ and not v4 and name == "Elements":
            _check_lines22(c, data, start.end())
        tags, nodes = _walk41(c, name) if v4 else _walk22(c, name)
        c.end()
        if name == "Nodes":
            _check_tags(tags, where, "node")
            _check_table(tags, where, 8 if v4 else 4)
            node_tags = np.sort(tags)
        else:
            _check_tags(tags, where, "element")
            _check_references(nodes, node_tags, where)


def _check_lines22(c: _Cursor, data: bytes, pos: int) -> None:
    """ASCII Gmsh 2.2 $Elements: every element line holds exactly the values its type and tag count say (a
    changed type would otherwise shift the values of the lines after it)."""
    end = data.find(b"$EndElements", pos)
    lines = data[pos : end if end >= 0 else len(data)].splitlines()[1:]
    for j, line in enumerate(lines, 1):
        f = line.split()
        if not f:
            continue
        try:
            need = 3 + int(f[2]) + _nodes_per_type(int(f[1]), c)
        except (IndexError, ValueError):
            c.fail(f"element line {j} is not 'tag type n_tags tags... nodes...'")
        if len(f) != need:
            c.fail(f"element line {j} (tag {f[0].decode(errors='replace')}) holds {len(f)} values, its type "
                   f"{int(f[1])} and {int(f[2])} tags need {need}")


def _walk41(c: _Cursor, name: str) -> tuple[np.ndarray, list]:
    """(tags, node tags of each element block) of a Gmsh 4.1 section."""
    n_blocks, total, _, _ = c.ints(4, c.size_t)
    held = 0
    tags, nodes = [], []
    for _ in range(n_blocks):
        dim, _, kind = c.ints(3, np.int32)
        (n,) = c.ints(1, c.size_t)
        held += n
        if name == "Nodes":
            tags.append(c.ints(n, c.size_t))
            c.skip(n * (3 + (int(dim) if kind else 0)), 8)
        else:
            k = _nodes_per_type(kind, c)
            rows = c.ints(n * (1 + k), c.size_t).reshape(n, 1 + k)
            tags.append(rows[:, 0])
            nodes.append(rows[:, 1:])
    if held != total:
        c.fail(f"the header announces {total} {name.lower()}, its {n_blocks} entity blocks hold {held}")
    return (np.concatenate(tags) if tags else np.zeros(0, np.int64)), nodes


def _walk22(c: _Cursor, name: str) -> tuple[np.ndarray, list]:
    """(tags, node tags of the elements) of a Gmsh 2.2 section."""
    if c.ascii:
        (total,) = c.ints(1, np.int32)
    else:
        m = re.compile(rb"\s*(\d+)[^\S\n]*\r?\n").match(c.data, c.pos)
        if m is None:
            c.fail("no count line")
        total, c.pos = int(m.group(1)), m.end()
    if name == "Nodes":
        if c.ascii:
            if c.i + 4 * total > len(c.tokens):
                c.fail(f"the header announces {total} nodes, the section holds fewer")
            tags = _as_ints(c, c.tokens[c.i : c.i + 4 * total : 4], "a node tag")
            c.i += 4 * total
        else:
            if c.pos + 28 * total > len(c.data):
                c.fail(f"the header announces {total} nodes, the file ends before them")
            rec = np.frombuffer(c.data, np.dtype([("tag", "i4"), ("xyz", "f8", 3)]), total, c.pos)
            tags = rec["tag"].astype(np.int64)
            c.pos += 28 * total
        return tags, []
    if c.ascii:
        tok, i = c.tokens, c.i
        ids, refs = [], []
        try:
            for _ in range(total):
                k, n_tags = _nodes_per_type(int(tok[i + 1]), c), int(tok[i + 2])
                ids.append(tok[i])
                refs.extend(tok[i + 3 + n_tags : i + 3 + n_tags + k])
                i += 3 + n_tags + k
        except (IndexError, ValueError):
            c.fail("fewer values than its headers announce")
        if i > len(tok):
            c.fail("fewer values than its headers announce")
        c.i = i
        return _as_ints(c, ids, "an element tag"), [_as_ints(c, refs, "a node tag")]
    held, tags, nodes = 0, [], []
    while held < total:
        t, follow, n_tags = (int(v) for v in c.ints(3, np.int32))
        if follow < 1:
            c.fail(f"an element block of {follow} elements")
        k = _nodes_per_type(t, c)
        rows = c.ints(follow * (1 + n_tags + k), np.int32).reshape(follow, 1 + n_tags + k)
        tags.append(rows[:, 0])
        nodes.append(rows[:, 1 + n_tags :])
        held += follow
    if held != total:
        c.fail(f"the header announces {total} elements, the blocks hold {held}")
    return (np.concatenate(tags) if tags else np.zeros(0, np.int64)), nodes


def _as_ints(c: _Cursor, tokens: list, what: str) -> np.ndarray:
    try:
        return np.array(tokens).astype(np.int64).reshape(-1)
    except (ValueError, OverflowError):
        c.fail(f"{what} is not an integer of at most 64 bits")


def _check_references(nodes: list, node_tags: np.ndarray | None, where: str) -> None:
    """Every node an element lists is a node tag of $Nodes."""
    if node_tags is None:
        raise MeshReadError(f"{where}: corrupt or truncated Gmsh file: $Elements but no $Nodes section")
    for block in nodes:
        flat = np.asarray(block, np.int64).reshape(-1)
        if not len(flat):
            continue
        pos = np.minimum(np.searchsorted(node_tags, flat), max(len(node_tags) - 1, 0))
        bad = node_tags[pos] != flat if len(node_tags) else np.ones(len(flat), bool)
        if bad.any():
            raise MeshReadError(f"{where}: an element of $Elements lists node tag {int(flat[bad][0])}, which $Nodes "
                                f"does not define ({int(bad.sum())} such references)")
