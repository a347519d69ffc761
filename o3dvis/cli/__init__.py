"""The ``o3dvis`` command. Each module listed in ``_MODULES`` adds its subcommands."""

from __future__ import annotations

import argparse
import importlib
import sys

__all__ = ["main", "build_parser"]

_MODULES = ("data", "visible", "eval", "apps", "demo")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="o3dvis", description="Neural visibility of point sets, for Open3D users.",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in _MODULES:
        importlib.import_module(f"{__name__}.{name}").register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (ValueError, TypeError, OSError, RuntimeError, ImportError) as e:
        message = str(e).strip().splitlines() or [type(e).__name__]
        print(f"o3dvis {args.command}: error: {message[0]}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
