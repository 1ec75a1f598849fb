"""DeepMerge: the learned registration network of scan pairs (docs/deepmerge.md).

``features`` builds the ``k x 14`` point structure, ``model`` is the network (PyTorch), ``register`` runs it on
two clouds in millimetres, ``shapes`` and ``train`` make the training data and fit the shipped weights. The
overlap, ICP, pose graph and whole-job correction it feeds are in ``pipeline.registration``.
"""
