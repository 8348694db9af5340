"""The interface stage: `smooth` (the one entry point) and what it runs on.

`methods` (the problem a method works on and the dispatch to it), `smooth` (`jaxci.smooth`: checks, untangling,
the method, the float64 guarantees), `engine` (which engine and device run it: `Plan`), `device_run` (a large
mesh kept on the device from upload to download), `invariants` (the checks every result passes), `result`
(`SmoothResult`), `seeds` (`jaxci.smooth_seeds`: several seeds of one mesh, global CI's as one program).
The public names are re-exported by `jaxci`; nothing is imported here.
"""
