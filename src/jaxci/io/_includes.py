"""Decks that include other files (Nastran ``INCLUDE``, LS-DYNA ``*INCLUDE``): the lines of a deck with its
included files inlined, where each line came from, and the files read (`HexMesh.input_files`).

A deck jaxci writes back holds the included lines in place of the include statement, so the included files are
only ever read, never written (`jaxci.io.write_mesh` also refuses to write over one).
"""

from __future__ import annotations

from collections.abc import Callable

from ..errors import MeshReadError
from ._deck import read_text
from ._paths import resolve_beside

#: How deep includes may nest (a deeper chain is a cycle).
MAX_DEPTH = 20

#: ``find(lines, i)`` -> None, or (the file named by the include statement that starts at line i, the number of
#: lines the statement takes).
Finder = Callable[[list[str], int], "tuple[str, int] | None"]


def flatten(path: str, find: Finder, what: str, depth: int = 0) -> tuple[list[str], list[tuple[str, int]], list[str]]:
    """The lines of the deck `path` (line endings kept) with its included files inlined, the (file, line number)
    of each, and the included files (resolved against the including file's folder).

    Raises `MeshReadError` naming the file and line of an include whose file is missing, or that nests deeper than
    `MAX_DEPTH` (a cycle).
    """
    lines = read_text(path, what, errors="surrogateescape").splitlines(keepends=True)
    out, origin, included = [], [], []
    i = 0
    while i < len(lines):
        found = find(lines, i)
        if found is None:
            out.append(lines[i])
            origin.append((path, i + 1))
            i += 1
            continue
        name, used = found
        at = f"{path}, line {i + 1}"
        if depth >= MAX_DEPTH:
            raise MeshReadError(f"{at}: includes nested more than {MAX_DEPTH} deep (a cycle?)")
        target = resolve_beside(name, path)
        if not target.is_file():
            raise MeshReadError(f"{at}: included file {name} not found (looked for {target})")
        sub, sub_origin, sub_inc = flatten(str(target), find, what, depth + 1)
        if sub and not sub[-1].endswith(("\n", "\r")):
            sub[-1] += "\n"
        out += sub
        origin += sub_origin
        included += [str(target), *sub_inc]
        i += used
    return out, origin, included
