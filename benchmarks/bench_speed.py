"""Timing of visibility methods against Open3D's HPR: the same as ``o3dvis bench``.

    python3 benchmarks/bench_speed.py --points 2048,8192,32768,81920,200000,1000000 --views 1,26 \\
        --methods hpr,hpr-exp,neural --out benchmarks/results/speed.json
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from o3dvis.cli.eval import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main("bench"))
