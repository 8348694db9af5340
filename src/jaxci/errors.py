"""Exception classes of jaxci.

Every error a user can cause (a bad file, a bad mesh, a bad config, a bad parameter) is raised as a subclass
of `JaxciError` with a one-sentence message that names the file, the element or the key at fault. The CLI maps
`JaxciError` to one line on stderr and exit code 2; library code never prints or exits.
"""

from __future__ import annotations


class JaxciError(Exception):
    """Base class of every error jaxci raises on purpose."""


class MeshError(JaxciError, ValueError):
    """A mesh is invalid: bad connectivity, non-finite coordinates, no hexahedra, ..."""


class MeshReadError(MeshError):
    """A mesh file could not be read: missing, unreadable, truncated or corrupt."""


class UnsupportedFormatError(MeshError):
    """A file extension or format name that jaxci cannot read or write."""


class MeshWriteError(JaxciError, OSError):
    """A mesh could not be written (unwritable folder, format that cannot hold the mesh, ...)."""


class InvertedMeshError(MeshError):
    """The mesh has inverted elements and the requested operation needs a valid (untangled) mesh."""


class ConfigError(JaxciError, ValueError):
    """An experiment config or a method parameter is invalid."""


class UsageError(JaxciError, TypeError):
    """A public function was called with an argument of the wrong type (a path or an array where a `HexMesh` is
    expected, a float seed, ...)."""
