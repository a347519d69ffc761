"""Accuracy of visibility methods on labelled data: the same as ``o3dvis eval``.

    python3 benchmarks/eval_accuracy.py --data data/val --points 2048,8192,32768,81920 \\
        --noise 0,0.01,0.02 --methods hpr,hpr-exp --views 16 --out benchmarks/results/val.json
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from o3dvis.cli.eval import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main("eval"))
