"""Jobs: the manager that queues and runs them (:mod:`.manager`; what a runner gets, :mod:`.context`; faults,
:mod:`.faults`), the runner that measures a plan (:mod:`.runner`, its records, state and journal), the
coordinate transfers and AGV relocalisation it makes, and the end of a job (the world map :mod:`.stitcher`,
:mod:`.finish`, :mod:`.correction`, :mod:`.outputs`). docs/daemon.md.
"""
