"""Evaluation beside training: how visibility methods score and how fast they run.

* :mod:`.evaluate`: accuracy against ray-cast labels on prepared samples (``o3dvis eval``).
* :mod:`.speed`: timing against Open3D's Hidden Point Removal in the same run (``o3dvis bench``).
* :mod:`.methods`: the benchmark's named methods (``hpr``, ``neural``, ``neural-x8`` ...).
* :mod:`.demo`: the network against Open3D's HPR on the shipped sample, as pictures (``o3dvis demo``).

It reads the labelled data of :mod:`o3dvis.training.data`; the runtime package never imports
this one, and the ``o3dvis`` commands that need it import it when they run.
"""
