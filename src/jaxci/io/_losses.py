"""What a mesh read from a solver deck loses when it is written afresh (`deck_losses`).

Apart from `jaxci.io._deck` (what the deck formats share, below both parsers) because it asks each parser what
its deck holds beyond the model: `jaxci.io._abaqus.deck_extras`, `jaxci.io._ansys_apdl.other_commands`.
"""

from __future__ import annotations

from ..mesh import HexMesh
from ._abaqus import deck_extras
from ._ansys_apdl import other_commands


def deck_losses(mesh: HexMesh, fmt: str) -> list[tuple[str, str]]:
    """What the source decks carried by `mesh` (field data ``abaqus:deck``, ``ansys:deck``) hold that a file of
    format `fmt` written afresh does not: ``(deck format, phrase)`` per deck, for a `LossyWriteWarning`."""
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
    return out


def _listed(names: list[str], most: int = 8) -> str:
    return ", ".join(names[:most]) + (f", ... ({len(names)} in all)" if len(names) > most else "")
