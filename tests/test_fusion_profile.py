"""benchmarks/profiling/fusion_profile.py: compiled ops timed from a real profiler trace, traced back to
their source lines, the count of ops running at once, and the training profile's loop regions."""

from pathlib import Path

import jax
import jax.numpy as jnp
import pytest
from benchmark_scripts import load_benchmark


def _fusion_profile():
    return load_benchmark("fusion_profile")


def test_ops_are_timed_and_traced_to_their_source(tmp_path):
    fp = _fusion_profile()
    f = jax.jit(lambda x: jnp.sort(x) * 2.0 + jnp.exp(x))
    x = jnp.linspace(1.0, 0.0, 1 << 16)
    f(x).block_until_ready()
    with jax.profiler.trace(str(tmp_path)):
        f(x).block_until_ready()
    events = fp.op_events(str(tmp_path))
    assert events and all(end >= start for start, end, _, _ in events)
    names = {name for *_, name in events}
    assert any(name.startswith("sort") for name in names), names
    assert not any("::" in name for name in names)  # runtime bookkeeping is not an op
    hlo = f.lower(x).compile().as_text()
    sources = fp.source_of(hlo)
    here = Path(__file__).name
    assert any(loc.startswith(f"{here}:") for name in names for loc in sources.get(name, [])), sources
    jax_ops = fp.jax_ops_of(hlo)  # what each op computes, where a custom VJP's backward loses its lines
    assert any(op.endswith("sort") for name in names for op in jax_ops.get(name, [])), jax_ops
    assert any(op.endswith("exp") for name in names for op in jax_ops.get(name, [])), jax_ops


def test_busy_threads_counts_overlapping_ops():
    fp = _fusion_profile()
    ms = 1_000_000  # events are in nanoseconds
    events = [(0, 10 * ms, "a", "x"), (5 * ms, 15 * ms, "b", "y"), (20 * ms, 30 * ms, "a", "z")]
    busy = fp.busy_threads(events)
    assert busy == pytest.approx(dict(idle_ms=5.0, one_busy_ms=20.0, two_or_more_busy_ms=5.0))
    assert fp.busy_threads([]) == dict(idle_ms=0.0, one_busy_ms=0.0, two_or_more_busy_ms=0.0)


def test_missing_trace_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="no profiler trace"):
        _fusion_profile().op_events(str(tmp_path))


def test_training_profile_tells_forward_from_backward_loops():
    """A differentiated loop compiles to two while loops: the training-step profile assigns each
    body's ops to the forward or the backward pass by the loop's op name."""
    fp = _fusion_profile()
    f = jax.jit(jax.grad(lambda x: jax.lax.fori_loop(0, 3, lambda i, c: jnp.sin(c) * c, x).sum()))
    hlo = f.lower(jnp.ones(8)).compile().as_text()
    bodies = fp._loop_bodies(hlo)
    assert sorted(bodies.values()) == ["backward", "forward"]
    owners = fp._owners(hlo)
    for body in bodies:
        assert any(owner == body for owner in owners.values())  # each body's ops are found
