"""jaxci: hexahedral mesh smoothing with Cohort Intelligence, batched in JAX."""

from importlib.metadata import PackageNotFoundError, version

from .errors import (
    ConfigError as ConfigError,
)
from .errors import (
    InvertedMeshError as InvertedMeshError,
)
from .errors import (
    JaxciError as JaxciError,
)
from .errors import (
    MeshError as MeshError,
)
from .errors import (
    MeshReadError as MeshReadError,
)
from .errors import (
    MeshWriteError as MeshWriteError,
)
from .errors import (
    UnsupportedFormatError as UnsupportedFormatError,
)
from .generate import PAPER_CASES as PAPER_CASES
from .generate import box as box
from .generate import paper_case as paper_case
from .generate import perturb_box as perturb_box
from .mesh import CellBlock as CellBlock
from .mesh import HexMesh as HexMesh
from .mesh import hex_mesh as hex_mesh

try:
    __version__ = version("jaxci")
except PackageNotFoundError:  # pragma: no cover
    __version__ = "0.0.0"
