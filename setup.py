"""The optional C extension `jaxci._ckernels` (the numpy path's fused kernels, `jaxci.native`); everything else
is in pyproject.toml. `optional=True`: without a C compiler the install still succeeds and jaxci uses numpy."""

from setuptools import Extension, setup

setup(ext_modules=[Extension("jaxci._ckernels", ["src/jaxci/_ckernels.c"], optional=True,
                             extra_compile_args=["-O3", "-std=c99", "-fno-trapping-math", "-pthread"],
                             extra_link_args=["-pthread"])])
