"""The ``o3dvis`` command. Each module listed in ``_MODULES`` adds its subcommands, those that work
on the user's files first, then those that make and measure models. Building the parser imports
nothing heavy: ``o3dvis --help`` and ``o3dvis --version`` answer at once."""

from __future__ import annotations

import argparse
import importlib
import sys

from ._common import split_vectors

__all__ = ["main", "build_parser"]

_MODULES = ("visible", "apps", "frames", "demo", "data", "eval")
_DESCRIPTION = """Neural visibility of point sets, for Open3D users.

Commands on your files: visible, normals, reconstruct, shadow, best-view, render, frames, demo.
Commands that make and measure models: shapes, prepare, train, calibrate, fuse, publish, eval,
eval-drives, bench.
'o3dvis COMMAND --help' tells what one does."""


def build_parser() -> argparse.ArgumentParser:
    from .. import __version__

    parser = argparse.ArgumentParser(prog="o3dvis", description=_DESCRIPTION,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"o3dvis {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in _MODULES:
        importlib.import_module(f"{__name__}.{name}").register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Runs the command line ``argv`` (default: ``sys.argv[1:]``).

    Returns:
        The exit code: 0, 1 where a command found nothing to do, 2 on a user error (a message,
        no traceback), 130 when interrupted.
    """
    args = build_parser().parse_args(split_vectors(sys.argv[1:] if argv is None else argv))
    try:
        return int(args.func(args) or 0)
    except (ValueError, TypeError, OSError, RuntimeError, ImportError) as e:
        message = str(e).strip().splitlines() or [type(e).__name__]
        print(f"o3dvis {args.command}: error: {message[0]}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"o3dvis {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
