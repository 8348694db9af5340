"""F, max kappa/3 and the gradient of F from the C kernel (`jaxci._ckernels`) inside compiled JAX programs on CPU.

The closed-form gradient in XLA (`jaxci.metrics.hexahedron.objective_terms_and_grad`) is a large program: XLA
materialises the corner arrays and scatters 24 of them into the nodes, compiles it for seconds, and, sharded over
several CPU devices, pays for the scatters on every device. `terms_and_grad` runs the C extension's loop over the
elements (float64) as an XLA FFI custom call (``jaxci_hex_terms_and_grad``, registered on first use), so the
compiled solvers (`jaxci.optim.gradient`, sharded or not) use it on CPU devices: no Python, no GIL, each device's
call on its own thread over its own elements (`jaxci.optim.sharding.sharded_terms_and_grad`). On GPUs, without the
extension, or with ``JAXCI_NATIVE=0`` they keep the XLA kernel.

Measured at 27,000 hexahedra on the 2-core CPU (a compiled loop of F and gradient calls, float32):
one device 5.4-6.3 ms per call against 5.3-6.6 ms for XLA's; four forced devices 4.3-5.1 ms against 6.0-7.4 ms
(XLA's sharded scatters), so four devices now cost what one does. The compilation of a whole L-BFGS run at 30^3
fell from 4.6-5.3 s to 2.9-3.0 s (one device) and 6.4-9.5 s to 3.5-4.9 s (four). (`jax.pure_callback` was tried
first: it puts its arguments on CPU device 0, which deadlocks a program sharded over several CPU devices.)
"""

from __future__ import annotations

import functools
import os

import numpy as np

from .. import native
from ..runtime import compile_cache
from ..runtime._lazy import jax, jnp

#: The custom call's name in XLA's registry.
TARGET = "jaxci_hex_terms_and_grad"


def available(platform: str) -> bool:
    """Whether `terms_and_grad` runs on devices of `platform` (``"cpu"``, ``"gpu"`` ...): the C extension is
    built and enabled with its FFI handler, the handler is registered (`refusal` says why not), and the arrays
    live in host memory (CPU devices)."""
    return native.AVAILABLE and platform == "cpu" and _registered()


def _header_version() -> tuple[int, int] | None:
    """``(major, minor)`` of XLA's FFI C API as the running jaxlib's own header declares it, or None where this
    jaxlib ships no header."""
    import re

    try:
        with open(os.path.join(jax.ffi.include_dir(), "xla", "ffi", "api", "c_api.h")) as f:
            text = f.read()
    except (OSError, AttributeError):
        return None
    found = [re.search(rf"#define XLA_FFI_API_{part} (\d+)", text) for part in ("MAJOR", "MINOR")]
    return None if None in found else (int(found[0].group(1)), int(found[1].group(1)))


_REFUSALS: list[str] = []


def refusal() -> str:
    """Why the handler is not registered (empty where it is, or was never tried)."""
    return _REFUSALS[-1] if _REFUSALS else ""


def check_version(built: tuple[int, int] | None, running: tuple[int, int] | None) -> str:
    """Why a handler built against XLA FFI API `built` must not be registered with a jaxlib whose header says
    `running` (empty: it may). The major versions must agree, and the handler's minor version must not be newer
    than the running one's; where the running jaxlib ships no header, the registration decides."""
    if built is None:
        return "the extension was built without XLA's FFI header (jax was not importable when it was built)"
    if running is None:
        return ""
    if built[0] != running[0] or built[1] > running[1]:
        return (f"the extension was built against XLA FFI API {built[0]}.{built[1]}, the running jaxlib speaks "
                f"{running[0]}.{running[1]}: rebuild it (pip install --force-reinstall --no-deps -e .)")
    return ""


@functools.cache
def _registered() -> bool:
    """Register the handler with XLA once, after checking the API version it was built against
    (`check_version`); False, with the reason in `refusal`, where either refuses (then XLA's kernel runs and the
    run's `jaxci.interface.engine.Plan` says so)."""
    why = check_version(native.ffi_api_version(), _header_version())
    if not why:
        try:
            jax.ffi.register_ffi_target(TARGET, native.ffi_handler(), platform="cpu")
            return True
        except Exception as e:  # noqa: BLE001 - an FFI API this build does not speak: fall back, never fail
            why = f"jax.ffi.register_ffi_target refused it: {type(e).__name__}: {e}"
    _REFUSALS.append(why)
    return False


compile_cache.register_target(TARGET, _registered)  # an exported program that calls it registers it first


def terms_and_grad(points, conn, weight=None, n_corners=None, threads: int | None = None):
    """``(F, max kappa/3, dF/dx)`` as `jaxci.metrics.hexahedron.objective_terms_and_grad` (F, not the p-mean),
    computed by the C kernel. Call only where `available` says so.

    **Arguments:** `points` ``(n, 3)`` float32 or float64 (the kernel computes in float64); `conn` the transposed
    connectivity ``(8, N)``, int32 or int64; `weight` optional ``(N,)``: elements of weight 0 (padding) are left
    out; `n_corners` (static): what F and its gradient are divided by (default: the real corners); `threads`
    (static): the kernel's threads (default `jaxci.native.THREADS`).

    **Returns:** F and max kappa/3 (scalars, ``inf`` if a corner has det <= 0; the gradient then leaves those
    corners out) and the gradient ``(n, 3)``, in the dtype of `points`.
    """
    if not _registered():
        raise RuntimeError(f"the XLA FFI target {TARGET} could not be registered: {refusal()}")
    dtype = points.dtype
    weight = jnp.ones(conn.shape[1], dtype) if weight is None else jnp.asarray(weight, dtype)
    params = np.array([0.0 if n_corners is None else float(n_corners),
                       native.THREADS if threads is None else int(threads)], dtype)
    shapes = (jax.ShapeDtypeStruct((), dtype), jax.ShapeDtypeStruct((), dtype),
              jax.ShapeDtypeStruct(points.shape, dtype))
    return jax.ffi.ffi_call(TARGET, shapes, vmap_method="sequential")(points, conn, weight, params)
