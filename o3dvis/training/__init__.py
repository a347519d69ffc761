"""Training beside the runtime: data preparation, training, calibration, publishing, evaluation.

The runtime package never imports this one; the ``o3dvis`` commands that need it import it
when they run.
"""
