"""jaxci: hexahedral mesh smoothing with Cohort Intelligence, batched in JAX."""

from importlib.metadata import PackageNotFoundError, version

from .errors import (
    ConfigError as ConfigError,
    InvertedMeshError as InvertedMeshError,
    JaxciError as JaxciError,
    MeshError as MeshError,
    MeshReadError as MeshReadError,
    MeshWriteError as MeshWriteError,
    UnsupportedFormatError as UnsupportedFormatError,
)
from .generate import PAPER_CASES as PAPER_CASES, box as box, paper_case as paper_case, perturb_box as perturb_box
from .mesh import CellBlock as CellBlock, HexMesh as HexMesh, hex_mesh as hex_mesh

try:
    __version__ = version("jaxci")
except PackageNotFoundError:  # pragma: no cover
    __version__ = "0.0.0"
