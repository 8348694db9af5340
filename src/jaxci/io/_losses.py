"""What a mesh read from a solver deck loses when it is written afresh (`deck_losses`).

Apart from `jaxci.io._deck` (what the deck formats share, below both parsers) because it asks each parser what
its deck holds beyond the model: `jaxci.io._abaqus.deck_extras`, `jaxci.io._ansys_apdl.other_commands`.
"""

from __future__ import annotations

from ..mesh import HexMesh
from ._abaqus import deck_extras
from ._ansys_apdl import other_commands

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


def _listed(names: list[str], most: int = 8) -> str:
    return ", ".join(names[:most]) + (f", ... ({len(names)} in all)" if len(names) > most else "")
