"""The daemon's gateways to the MES and operators, both over one service facade (:mod:`.facade`): the REST API
(:mod:`.app`, its routers in :mod:`.routers`, wire models :mod:`.models`, problem details :mod:`.errors`, the token
and body guard :mod:`.guard`), the operator console (:mod:`.console`) and, beside REST, the OPC UA server
(:mod:`.opcua`). See docs/daemon.md, docs/rest-api.md, docs/opcua.md.
"""
