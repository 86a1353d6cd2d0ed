"""The host memory policy: freed large blocks are reused without new page faults."""

import os
import subprocess
import sys
import textwrap

import pytest

from ghsplat_jax import host_memory

# Allocates and frees a 64 MB block a few times, reports the page faults of the last rounds.
PROBE = textwrap.dedent("""
    import resource, numpy as np
    from ghsplat_jax.host_memory import reuse_freed_memory
    applied = reuse_freed_memory()
    def rounds():
        f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        for _ in range(4):
            block = np.ones(16 * 2**20, np.float32)
            del block
        return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0
    rounds()
    print(int(applied), rounds())
""")


def _probe(env_extra: dict) -> tuple[bool, int]:
    env = dict(os.environ, **env_extra)
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, env=env, check=True)
    applied, faults = out.stdout.split()
    return applied == "1", int(faults)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="a glibc malloc policy")
def test_freed_blocks_are_reused_without_page_faults():
    applied, faults = _probe({host_memory.OPT_OUT: "0"})
    if not applied:
        pytest.skip("not glibc")
    kept_applied, system_faults = _probe({host_memory.OPT_OUT: "1"})
    assert not kept_applied
    # With the system policy every round maps and faults the block in again.
    assert system_faults > 50
    assert faults < system_faults / 20


@pytest.mark.skipif(not os.path.exists("/proc/self/maps"), reason="Linux's per-process mapping count")
def test_compiled_programs_are_released_near_the_mapping_limit_and_their_mappings_go():
    import jax
    import jax.numpy as jnp

    def compile_some(n):
        for i in range(n):
            jax.jit(lambda x, i=i: jnp.cumsum(x) * i)(jnp.ones(7 + i)).block_until_ready()

    count, limit = host_memory.memory_maps()
    assert 0 < count < limit
    assert not host_memory.release_compiled_programs(share=1.0)  # under the limit: nothing dropped
    compile_some(40)
    before = host_memory.memory_maps()[0]
    assert host_memory.release_compiled_programs(share=0.0)
    assert host_memory.memory_maps()[0] < before - 40  # each program held mappings of its own
