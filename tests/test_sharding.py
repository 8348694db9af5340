"""The XLA:CPU thread pool of a multi-device process (4 forced CPU devices in a subprocess)."""

from __future__ import annotations

import subprocess
import sys

import pytest
from helpers import cpu_env


def _pool_threads(devices: int, nproc: str) -> int:
    env = dict(cpu_env(devices), NPROC=nproc)
    env.pop("PJRT_NPROC", None)
    code = "from jaxci.optim.sharding import xla_cpu_threads; print('THREADS', xla_cpu_threads())"
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-3000:]
    return int(r.stdout.split("THREADS")[-1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="counts threads in /proc")
def test_xla_cpu_pool_has_at_least_one_thread_per_device():
    """XLA:CPU's intra-op pool is max(NPROC, device count) threads, so forced devices oversubscribe a
    small CPU whatever NPROC says (the measured 4-device slowdown; docs/sharding.md)."""
    assert _pool_threads(1, "1") == 1
    assert _pool_threads(1, "3") == 3
    assert _pool_threads(3, "1") == 3  # NPROC cannot lower it below the device count
