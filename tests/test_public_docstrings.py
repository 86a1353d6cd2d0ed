"""Every name the public facade (ghsplat_jax/__init__.py) exports documents its arguments and
what it returns, Google style (`Args:` and `Returns:` sections); a function's `Args:` names
each of its parameters."""

import inspect
import re
import subprocess
import sys

import pytest

import ghsplat_jax as gs


def section(doc: str, name: str) -> str | None:
    """The text of a Google-style section (`name:` alone on a line) up to the next one."""
    match = re.search(rf"^\s*{name}:\s*$(.*?)(?=^\s*[A-Z][A-Za-z ]*:\s*$|\Z)", doc, re.MULTILINE | re.DOTALL)
    return None if match is None else match.group(1)


def test_the_facade_exports_what_it_lists():
    assert sorted(gs.__all__) == sorted(set(gs.__all__))
    for name in gs.__all__:
        assert callable(getattr(gs, name)), name


@pytest.mark.parametrize("name", gs.__all__)
def test_exported_callable_has_args_and_returns(name):
    obj = getattr(gs, name)
    doc = inspect.getdoc(obj) or ""
    args, returns = section(doc, "Args"), section(doc, "Returns")
    assert args and args.strip(), f"gs.{name}: no 'Args:' section in its docstring"
    assert returns and returns.strip(), f"gs.{name}: no 'Returns:' section in its docstring"
    if inspect.isfunction(obj):
        params = [p for p in inspect.signature(obj).parameters if p not in ("self", "args", "kwargs")]
        missing = [p for p in params if not re.search(rf"\b{p}\b", args)]
        assert not missing, f"gs.{name}: 'Args:' does not name {missing}"


def test_the_section_reader_finds_sections():
    doc = "Summary.\n\nArgs:\n    x: a value.\n\nReturns:\n    y.\n"
    assert section(doc, "Args").strip() == "x: a value."
    assert section(doc, "Returns").strip() == "y."
    assert section("Summary only.", "Args") is None


def test_the_facade_loads_jax_only_when_used():
    # Report scripts import the package's JAX-free modules (io_utils, curves) for their README checks.
    code = ("import sys, ghsplat_jax.io_utils, ghsplat_jax.curves; assert 'jax' not in sys.modules, 'jax loaded'; "
            "import ghsplat_jax as gs; assert 'render' in dir(gs); gs.render; assert 'jax' in sys.modules; "
            "from ghsplat_jax import load_ply\n"
            "try:\n    gs.no_such_name\nexcept AttributeError as e:\n    print(e)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert "has no attribute 'no_such_name'" in out.stdout
