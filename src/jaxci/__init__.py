"""jaxci: hexahedral mesh smoothing with Cohort Intelligence, batched in JAX.

The public API. The errors, the mesh model and `smooth` (`jaxci.interface.smooth`) are imported at once; the rest
of the JAX-side API (I/O, quality kernels, constraints, CI parameters, `smooth_seeds`) is loaded on first use.
"""

# ruff: noqa: E402  (the re-exec of the jaxci command must come before the imports below)
from .runtime import process as _process

_process.reexec_with_hugepages()  # the jaxci command only: huge pages for XLA's buffers (jaxci.runtime.process)
_process.quiet_interrupts_while_starting()  # the jaxci command only: Ctrl-C while importing exits 130, quietly
_process.single_threaded_blas()  # the jaxci command only: no OpenBLAS threads spinning beside the C kernels

from importlib import import_module

from .errors import (
    ConfigError,
    InvertedMeshError,
    JaxciError,
    MeshError,
    MeshReadError,
    MeshWriteError,
    UnsupportedFormatError,
    UsageError,
)
from .interface.smooth import METHODS, SmoothResult, smooth
from .mesh import CellBlock, HexMesh, hex_mesh, merge_coincident
from .mesh.generate import PAPER_CASES, box, paper_case, perturb_box

#: name -> module of the lazily loaded public API.
_LAZY = {
    "read_mesh": "io",
    "write_mesh": "io",
    "quality_report": "metrics.report",
    "QualityReport": "metrics.report",
    "objective": "metrics.hexahedron",
    "corner_condition": "metrics.hexahedron",
    "element_condition": "metrics.hexahedron",
    "element_scaled_jacobian": "metrics.hexahedron",
    "classify_boundary": "geometry.boundary",
    "BoundaryInfo": "geometry.boundary",
    "build_constraints": "geometry.projection",
    "project": "geometry.projection",
    "project_np": "geometry.projection",
    "CIParams": "optim.ci",
    "init_distributed": "optim.sharding",
    "smooth_seeds": "interface.seeds",
}

__all__ = [
    "CellBlock", "ConfigError", "HexMesh", "InvertedMeshError", "JaxciError", "MeshError", "MeshReadError",
    "MeshWriteError", "PAPER_CASES", "UnsupportedFormatError", "UsageError", "box", "hex_mesh", "merge_coincident",
    "paper_case", "perturb_box",
    "METHODS", "SmoothResult", "smooth",
    *_LAZY,
]


def __getattr__(name: str):
    if name == "__version__":  # from the installed metadata on first use: importing importlib.metadata takes
        # 20 ms, a tenth of the jaxci command's start on this machine, and only --version and reports need it
        from importlib.metadata import PackageNotFoundError, version

        try:
            value = version("jaxci")
        except PackageNotFoundError:  # pragma: no cover
            value = "0.0.0"
        globals()[name] = value
        return value
    if name in _LAZY:
        value = getattr(import_module(f".{_LAZY[name]}", __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'jaxci' has no attribute {name!r}")
