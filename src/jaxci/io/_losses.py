"""What a mesh read from a solver deck loses when it is written afresh (`deck_losses`).

Apart from `jaxci.io._deck` (what the deck formats share, below both parsers) because it asks each parser what
its deck holds beyond the model: `jaxci.io._abaqus.deck_extras`, `jaxci.io._ansys_apdl.other_commands`.
"""

from __future__ import annotations

from ..mesh import HexMesh
from ._abaqus import deck_extras
from ._ansys_apdl import other_commands
from ._fields import rewrite_deck

#: Field data that carry a source file (its text, or its path for a format written back from the file itself),
#: not data of the mesh: never reported as lost field data; `deck_losses` says what each means.
SOURCE_FIELDS = ("abaqus:deck", "abaqus:element_types", "ansys:deck", "nastran:deck", "lsdyna:deck", "exodus:file")

#: What the source files of the formats without a lister of their own hold beyond the mesh (deck format, phrase).
_SOURCES = {
    "nastran:deck": ("nastran", "the other cards of the source Nastran deck (properties, materials, loads, "
                                "coordinate systems, case control)"),
    "lsdyna:deck": ("lsdyna", "the other keywords of the source LS-DYNA deck (*PART, *SECTION, *MAT, loads, "
                              "controls)"),
    "exodus:file": ("exodus", "the results, side sets, attributes, maps, QA and info records of the source Exodus "
                              "file"),
}

def deck_losses(mesh: HexMesh, fmt: str) -> list[tuple[str, str]]:
    """What the source files carried by `mesh` (`SOURCE_FIELDS`) hold that a file of format `fmt` written afresh
    does not: ``(deck format, phrase)`` per source, for a `LossyWriteWarning` (a writer of the source's own format
    that writes the file back in place leaves its own out)."""
    out = []
    deck = mesh.field_data.get("abaqus:deck")
    if isinstance(deck, str):
        keywords, types = deck_extras(deck)
        if fmt == "abaqus":
            types = []  # a fresh Abaqus deck keeps the element types
        what = ([f"the keyword blocks {_listed(keywords)}"] if keywords else []) + (
            [f"the element types {', '.join(types)}"] if types else [])
        if what:
            out.append(("abaqus", f"{' and '.join(what)} of the source Abaqus deck"))
    deck = mesh.field_data.get("ansys:deck")
    if isinstance(deck, str):
        commands = other_commands(deck)
        if commands:
            out.append(("apdl", f"the other APDL commands of the source file ({_listed(commands)})"))
    out += [_SOURCES[k] for k in _SOURCES if mesh.field_data.get(k)]
    return out


def _listed(names: list[str]) -> str:
    return ", ".join(names[:8]) + (f", ... ({len(names)} in all)" if len(names) > 8 else "")


def data_losses(mesh: HexMesh, own_cell_data: tuple = ()) -> list[str]:
    """The data of `mesh` a file that keeps none leaves out: point data, cell data but `own_cell_data` (a deck's
    own, e.g. ``nastran:pid``), field data but the sources' (`SOURCE_FIELDS`)."""
    lost = [f"point data {sorted(mesh.point_data)}"] if mesh.point_data else []
    cell = sorted(k for k in mesh.cell_data if k not in own_cell_data)
    if cell:
        lost.append(f"cell data {cell}")
    field = sorted(k for k in mesh.field_data if k not in SOURCE_FIELDS)
    if field:
        lost.append(f"field data {field}")
    return lost


def dropped_data(mesh: HexMesh, fmt: str, own_cell_data: tuple = ()) -> list[str]:
    """What a file of format `fmt` written from `mesh` leaves out of it: its `data_losses`, and what other sources'
    files hold (`deck_losses`; the file's own source is the writer's to report)."""
    return data_losses(mesh, own_cell_data) + [what for f, what in deck_losses(mesh, fmt) if f != fmt]


def deck_text(mesh: HexMesh, path: str, fmt: str, fresh, parse_deck, node: str, nastran: bool
              ) -> tuple[str, list[str]]:
    """The text of a deck of format `fmt` (``"nastran"``, ``"lsdyna"``) for `mesh`, and what it leaves out: the
    mesh's source deck (field data ``FMT:deck``) with new coordinates where `jaxci.io._fields.rewrite_deck` can
    write it in place (``parse_deck``, `node` and `nastran` as it takes them; the property ids in cell data
    ``FMT:pid``), else ``fresh(mesh, path)`` (``(text, lost)``; the mesh's sets are left out)."""
    deck = mesh.field_data.get(f"{fmt}:deck")
    lost, text = [], None
    if isinstance(deck, str):
        reason, text = rewrite_deck(mesh, deck, path, parse_deck, f"{fmt}:pid", node, nastran)
        if text is None:
            lost.append(f"{_SOURCES[f'{fmt}:deck'][1]} ({reason}, so the deck cannot be rewritten in place)")
    if text is None:
        text, more = fresh(mesh, path)
        lost += more + [f"{what} {sorted(d)}" for what, d in (("point sets", mesh.point_sets),
                                                             ("cell sets", mesh.cell_sets)) if d]
    return text, lost + dropped_data(mesh, fmt, (f"{fmt}:pid",))

