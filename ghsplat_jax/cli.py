"""The `ghsplat` command. Each subcommand lives in its own module, imported on use,
so `ghsplat train` never pays for pycolmap or cyclonedds imports.

A command module defines `HELP` (one line), `add_arguments(parser)` and `main(args) -> int`.
"""

from __future__ import annotations

import argparse
import importlib
import sys

COMMANDS = {
    "demo": "ghsplat_jax.commands.demo",
    "render": "ghsplat_jax.commands.render",
    "sfm": "ghsplat_jax.sfm.command",
    "train": "ghsplat_jax.commands.train",
    "eval": "ghsplat_jax.eval.command",
    "run": "ghsplat_jax.eval.run_command",
    "export": "ghsplat_jax.scene.export_command",
    "compose": "ghsplat_jax.scene.compose_command",
    "simulate": "ghsplat_jax.sim.command",
    "localize": "ghsplat_jax.sim.localize_command",
    "synth": "ghsplat_jax.synth.command",
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


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    commands = _available()
    args = build_parser(commands).parse_args(argv)
    try:
        return int(args._module.main(args) or 0)
    except KeyboardInterrupt:
        print("ghsplat: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
