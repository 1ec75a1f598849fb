"""The REST API's routes, one router per resource, each a thin gateway over the service facade
(:mod:`tandemscan.daemon.api.facade`): ``jobs``, ``files`` (a job's outputs), ``cell`` (devices, safety,
calibration, plans), ``events`` (server-sent events) and ``health`` (health, metrics). See docs/daemon.md.
"""
