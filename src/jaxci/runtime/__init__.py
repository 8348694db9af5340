"""The process and JAX runtime every stage builds on (stage "base" of the README's Architecture).

`process` (the jaxci command's start-up: huge pages, quiet Ctrl-C while importing, one BLAS thread, the CPUs it
may use), `_lazy` (JAX imported on first use: the numpy path never imports it), `phases` (phase timing and
progress events), `memory` (memory estimates checked before work), `transfer` (the JAX engine's host-device
transfers and time in compiled programs, counted), `sizes` (the size classes compiled programs are padded to),
`compile_cache`, `_export` and `_keys` (compilation once per machine: the cache folder, compiled entry points kept
as `jax.export` programs, and their keys). Nothing is imported here: ``import jaxci`` loads `process` alone first.
"""
