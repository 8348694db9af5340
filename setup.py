"""The optional C extension `jaxci._ckernels` (the host engine's fused kernels, `jaxci.native`); everything else
is in pyproject.toml. `optional=True`: without a C compiler the install still succeeds and jaxci uses numpy.

The extension's XLA FFI handler (`jaxci.metrics.native_grad`) is built against XLA's FFI C header as the jaxlib
of the build environment ships it (``jax.ffi.include_dir()``; jax and jaxlib are build requirements); where that
cannot be imported the extension is built without the handler and the JAX engine keeps XLA's kernel."""

from setuptools import Extension, setup


def _ffi_include() -> list[str]:
    try:
        import jax.ffi

        return [jax.ffi.include_dir()]
    except Exception:  # noqa: BLE001 - no jax at build time: the kernels without the FFI handler
        return []


_include = _ffi_include()
setup(ext_modules=[Extension("jaxci._ckernels", ["src/jaxci/_ckernels.c", "src/jaxci/_pool.c"], optional=True,
                             include_dirs=_include, define_macros=[("JAXCI_XLA_FFI", "1")] if _include else [],
                             extra_compile_args=["-O3", "-std=c99", "-fno-trapping-math", "-pthread"],
                             extra_link_args=["-pthread"])])
