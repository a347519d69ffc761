"""The hypothesis properties of tests/test_fuzz.py on fresh random cases, for longer than CI.

Each round runs every property (or those ``--only`` names) once at its CI size (about 1 430
cases in all) with a new random seed; rounds go on until ``--minutes`` or ``--examples`` is
reached. Prints the number of cases run per property and in total; exits 1 with hypothesis's
falsifying example when a property fails (a process that dies prints no summary).

    nice -n 10 python3 benchmarks/fuzz_long.py --minutes 5
    python3 benchmarks/fuzz_long.py --examples 20000 --minutes 0
    python3 benchmarks/fuzz_long.py --only header --only cli_reads --examples 10000 --minutes 0
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import traceback
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]
os.environ["O3DVIS_FUZZ_RANDOM"] = "1"  # read when test_fuzz is imported: fresh cases every round

import torch  # noqa: E402
import test_fuzz  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--minutes", type=float, default=5.0, help="stop after this long (0: no limit)")
    parser.add_argument("--examples", type=int, default=20_000, help="stop after this many cases")
    parser.add_argument("--only", action="append", default=[], metavar="TEXT",
                        help="run only the properties whose name holds TEXT (repeatable; default: all)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    properties = [getattr(test_fuzz, name) for name in dir(test_fuzz)
                  if name.startswith("test_") and (not args.only or any(text in name for text in args.only))]
    if not properties:
        parser.error(f"no property of tests/test_fuzz.py has {' or '.join(args.only)} in its name")
    start, rounds = time.monotonic(), 0
    while sum(test_fuzz.COUNTS.values()) < args.examples and (
            not args.minutes or time.monotonic() - start < 60 * args.minutes):
        for prop in properties:
            try:
                prop()
            except Exception:
                traceback.print_exc()
                print(json.dumps({"failed": prop.__name__, "cases": dict(test_fuzz.COUNTS)}))
                return 1
        rounds += 1
    print(json.dumps({"rounds": rounds, "seconds": round(time.monotonic() - start, 1),
                      "cases": dict(test_fuzz.COUNTS), "total": sum(test_fuzz.COUNTS.values())}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
