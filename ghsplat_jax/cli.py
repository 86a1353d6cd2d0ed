"""The `ghsplat` command. Each subcommand lives in its own module, imported on use,
so `ghsplat train` never pays for pycolmap or cyclonedds imports.

A command module defines `HELP` (one line), `add_arguments(parser)` and `main(args) -> int`.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from pathlib import Path

from ghsplat_jax.host_memory import reuse_freed_memory

COMMANDS = {
    "demo": "ghsplat_jax.commands.demo",
    "render": "ghsplat_jax.commands.render",
    "sfm": "ghsplat_jax.commands.sfm",
    "train": "ghsplat_jax.commands.train",
    "eval": "ghsplat_jax.commands.eval",
    "run": "ghsplat_jax.commands.run",
    "export": "ghsplat_jax.commands.export",
    "compose": "ghsplat_jax.commands.compose",
    "simulate": "ghsplat_jax.commands.simulate",
    "localize": "ghsplat_jax.commands.localize",
    "synth": "ghsplat_jax.commands.synth",
    "bench": "ghsplat_jax.commands.bench",
}


def _available() -> dict[str, object]:
    found = {}
    for name, module in COMMANDS.items():
        try:
            found[name] = importlib.import_module(module)
        except ModuleNotFoundError as exc:
            if exc.name and module.startswith(exc.name):
                continue  # that command is not built yet
            raise
    return found


def build_parser(commands: dict[str, object]) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="ghsplat", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    for name, module in commands.items():
        p = sub.add_parser(name, help=module.HELP, description=module.HELP)
        module.add_arguments(p)
        p.set_defaults(_module=module)
    return parser


def _enable_compilation_cache() -> None:
    """Compiled XLA programs persist across commands (training steps take tens of seconds to
    compile): $JAX_COMPILATION_CACHE_DIR when set, else ~/.cache/ghsplat-jax/xla."""
    import jax

    if not jax.config.jax_compilation_cache_dir:
        default = Path.home() / ".cache" / "ghsplat-jax" / "xla"
        jax.config.update("jax_compilation_cache_dir", os.environ.get("JAX_COMPILATION_CACHE_DIR") or str(default))


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    commands = _available()
    args = build_parser(commands).parse_args(argv)
    _enable_compilation_cache()
    reuse_freed_memory()
    try:
        return int(args._module.main(args) or 0)
    except KeyboardInterrupt:
        print("ghsplat: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
