"""``python -m gateway.schema --write``: regenerate the example configuration and the
reference page from the schema; ``--check``: exit 1 when a committed copy drifted."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .render import REGENERATE, drifted, write

#: The checkout's root: the copies live beside the package (conf/, docs/, gateway/data/).
ROOT = Path(__file__).resolve().parents[2]


def main(argv: list[str] | None = None) -> int:
    """Write or check the copies under the checkout's root."""
    parser = argparse.ArgumentParser(prog="python -m gateway.schema", description=__doc__)
    mode = parser.add_mutually_exclusive_group(required=True)
    mode.add_argument("--write", action="store_true", help="write the copies that drifted")
    mode.add_argument("--check", action="store_true", help="exit 1 when a copy drifted")
    parser.add_argument("--root", type=Path, default=ROOT, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.write:
        for path in write(args.root):
            print(f"wrote {path}")
        return 0
    stale = drifted(args.root)
    for path in stale:
        print(f"{path} differs from the schema; run: {REGENERATE}", file=sys.stderr)
    return 1 if stale else 0


if __name__ == "__main__":
    sys.exit(main())
