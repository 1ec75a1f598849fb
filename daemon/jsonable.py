"""Plain JSON values from what devices and runs report: numpy arrays and scalars, dataclasses, enums, paths, bytes.

Device status details (a chassis pose dataclass, a safety state, an enum mode) are journaled and sent over SSE
(``docs/daemon.md``, events); everything goes through :func:`jsonable` first so that no event fails to serialise.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from pathlib import PurePath

import numpy as np


def jsonable(value: object) -> object:
    """``value`` as JSON-encodable dicts, lists, strings, numbers, booleans and None (non-finite floats: None)."""
    if isinstance(value, enum.Enum):
        return jsonable(value.value)
    if isinstance(value, (bool, int, str)) or value is None:
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    if isinstance(value, np.generic):
        return jsonable(value.item())
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, set, frozenset)):
        return [jsonable(v) for v in value]
    if isinstance(value, (bytes, bytearray)):
        return value.hex()
    if isinstance(value, PurePath):
        return str(value)
    return str(value)
