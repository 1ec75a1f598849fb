"""DeepMerge: learned correction of the tracker stitch from the overlap of scan pairs (DESIGN.md 5.5).

``overlap`` finds the overlap after the initial stitch, ``features`` builds the ``k x 14`` point
structure, ``model`` is the network (PyTorch), ``register`` runs it on two clouds in millimetres and
``train`` makes the training data and fits the shipped weights.
"""
