"""What the bad-input matrix, the files refused and the extremes share."""

import numpy as np

CAMERA = np.array([0.4, -0.3, 3.0])
GRID = np.stack(np.meshgrid(np.linspace(0, 1, 12), np.linspace(0, 2, 12)), axis=-1).reshape(-1, 2)
PLANE = np.c_[GRID, np.zeros(len(GRID))]
_CHILD_TIMEOUT = 240
