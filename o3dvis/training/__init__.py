"""Training beside the runtime: data preparation, training, calibration, fusion, publishing.

The runtime package never imports this one; the ``o3dvis`` commands that need it import it
when they run. How trained models score and how fast they run is :mod:`o3dvis.evaluation`.
"""
