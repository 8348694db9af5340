"""The ladder of size classes (numpy-free, JAX-free): `bucket`.

A shape that depends on the data (a mesh's elements, the boundary faces a device program finds) is padded to
the next size of the ladder ``8, 12, 16, 24, 32, 48, 64, ...`` (powers of two and 1.5 times powers of two: at
most 50% and on average about 20% padding), so that inputs of similar size share one compiled program.
`jaxci.optim._buckets` describes how the solvers pad to it; the device programs of `jaxci.geometry` size the
arrays they bring down by it.
"""

from __future__ import annotations

#: The smallest size of the ladder.
MIN_BUCKET = 8


def bucket(n: int, minimum: int = MIN_BUCKET, multiple: int = 1) -> int:
    """The smallest size of the ladder ``minimum, ..., 2^k, 3 * 2^(k-1), 2^(k+1), ...`` that is at least `n`
    (0 stays 0: an empty class keeps its static branch), rounded up to a multiple of `multiple` (the device
    count of a sharded run, `jaxci.optim.sharding`: every device gets as many elements)."""
    n = int(n)
    if n <= 0:
        return 0
    n = max(n, int(minimum))
    p = 1 << (n - 1).bit_length()  # the power of two >= n
    q = 3 * p // 4
    b = q if q >= n and p >= 4 else p
    return -(-b // int(multiple)) * int(multiple)
