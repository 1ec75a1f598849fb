"""The OPC UA server beside the REST API (``[opcua] enabled``): the address space (:mod:`.model`), its variables
fed from the daemon's events (:mod:`.feed`), job and safety methods (:mod:`.server`, :mod:`.calls`), result
transfer (:mod:`.results`) and security (:mod:`.security`). See docs/opcua.md.
"""
