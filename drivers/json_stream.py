"""Split a TCP byte stream into JSON objects (JAKA sends objects back to back with no length prefix).

The framer tracks brace depth outside string literals, so an object is complete exactly when its closing
brace arrives, however the bytes were split by the network.
"""

from __future__ import annotations

import json


class JsonFramingError(ValueError):
    """The stream holds something that is not a JSON object, or an object larger than the limit."""


class JsonObjectFramer:
    """Feed bytes in, get complete JSON objects (dicts) out, in order.

    ``max_object_bytes`` bounds the memory a misbehaving peer can make us hold.
    """

    def __init__(self, max_object_bytes: int = 1 << 20):
        self._buf = bytearray()
        self._max = max_object_bytes
        self._depth = 0
        self._in_string = False
        self._escape = False
        self._scan = 0  # bytes of _buf already scanned

    @property
    def pending(self) -> bool:
        """True while a partial object is buffered (a close now would truncate it)."""
        return any(b not in b" \t\r\n" for b in self._buf)

    def feed(self, data: bytes) -> list[dict]:
        """Add ``data``; return every object it completes. Raises :class:`JsonFramingError` on garbage."""
        self._buf += data
        out: list[dict] = []
        i = self._scan
        while i < len(self._buf):
            c = self._buf[i]
            if self._depth == 0:
                if c in b" \t\r\n":
                    del self._buf[: i + 1]
                    i = 0
                    continue
                if c != ord("{"):
                    self._reset()
                    raise JsonFramingError(f"unexpected byte {bytes([c])!r} between objects")
            if self._in_string:
                if self._escape:
                    self._escape = False
                elif c == ord("\\"):
                    self._escape = True
                elif c == ord('"'):
                    self._in_string = False
            elif c == ord('"'):
                self._in_string = True
            elif c == ord("{") or c == ord("["):
                self._depth += 1
            elif c == ord("}") or c == ord("]"):
                self._depth -= 1
                if self._depth == 0:
                    out.append(self._decode(bytes(self._buf[: i + 1])))
                    del self._buf[: i + 1]
                    i = 0
                    continue
            i += 1
        self._scan = i
        if len(self._buf) > self._max:
            self._reset()
            raise JsonFramingError(f"object larger than {self._max} bytes")
        return out

    def _decode(self, raw: bytes) -> dict:
        try:
            obj = json.loads(raw, parse_constant=_reject_constant)
        except (ValueError, UnicodeDecodeError) as e:
            self._reset()
            raise JsonFramingError(f"invalid JSON object: {e}") from e
        if not isinstance(obj, dict):
            self._reset()
            raise JsonFramingError("top-level value is not an object")
        return obj

    def _reset(self) -> None:
        self._buf.clear()
        self._depth = 0
        self._in_string = False
        self._escape = False
        self._scan = 0


def _reject_constant(name: str) -> float:
    raise ValueError(f"non-finite number {name}")


def encode(obj: dict) -> bytes:
    """One JSON object as bytes (no separator: the peer frames by object)."""
    return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()
