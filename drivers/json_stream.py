"""Split a TCP byte stream into JSON objects (JAKA sends objects back to back with no length prefix).

The framer tracks brace depth outside string literals, so an object is complete exactly when its closing
brace arrives, however the bytes were split or coalesced by the network. The scan runs at C speed: a
regular expression jumps to the next brace, bracket or quote, ``bytes.find`` to the end of a string literal,
so the Python loop runs once per brace, bracket or string, not once per byte (a 6 kB JAKA status object has a
few hundred of them); each complete object is then decoded by ``json.loads``.
"""

from __future__ import annotations

import json
import re

_STRUCTURAL = re.compile(rb'["{}\[\]]')
_WHITESPACE = b" \t\r\n"
_QUOTE, _BACKSLASH, _OPENING = ord('"'), ord("\\"), (ord("{"), ord("["))


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
        self._scan = 0  # bytes of the current object already scanned (always at a token boundary)

    @property
    def pending(self) -> bool:
        """True while a partial object is buffered (a close now would truncate it)."""
        return bool(self._buf.strip(_WHITESPACE))

    def feed(self, data: bytes) -> list[dict]:
        """Add ``data``; return every object it completes. Raises :class:`JsonFramingError` on garbage."""
        self._buf += data
        buf = self._buf
        out: list[dict] = []
        start = 0  # where the current object begins in buf
        pos = self._scan
        depth = self._depth
        if depth == 0:
            pos = start = self._object_start(buf, 0)
        while pos < len(buf):
            m = _STRUCTURAL.search(buf, pos)
            if m is None:
                pos = len(buf)
                break
            i = m.start()
            if buf[i] == _QUOTE:
                end = _string_end(buf, i)
                if end < 0:
                    pos = i  # a string cut off by the end of the buffer: rescan it with more bytes
                    break
                pos = end + 1
                continue
            depth += 1 if buf[i] in _OPENING else -1
            pos = i + 1
            if depth == 0:
                out.append(self._decode(bytes(buf[start:pos])))
                pos = start = self._object_start(buf, pos)
        del buf[:start]
        self._scan, self._depth = pos - start, depth
        if len(buf) > self._max:
            self._reset()
            raise JsonFramingError(f"object larger than {self._max} bytes")
        return out

    def _object_start(self, buf: bytearray, pos: int) -> int:
        """Index of the next object's opening brace at or after ``pos`` (whitespace may come first), or
        ``len(buf)`` when only whitespace follows; anything else between objects is a framing error."""
        n = len(buf)
        while pos < n and buf[pos] in _WHITESPACE:
            pos += 1
        if pos < n and buf[pos] != ord("{"):
            bad = bytes(buf[pos : pos + 1])
            self._reset()
            raise JsonFramingError(f"unexpected byte {bad!r} between objects")
        return pos

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
        self._scan = 0


def _string_end(buf: bytearray, start: int) -> int:
    """Index of the quote that closes the string literal opening at ``start``, or -1 if it is not in ``buf``
    yet. A quote after an odd run of backslashes is escaped."""
    end = buf.find(b'"', start + 1)
    while end >= 0:
        k = end - 1
        while buf[k] == _BACKSLASH:  # stops at the opening quote at the latest
            k -= 1
        if (end - 1 - k) % 2 == 0:
            return end
        end = buf.find(b'"', end + 1)
    return -1


def _reject_constant(name: str) -> float:
    raise ValueError(f"non-finite number {name}")


def encode(obj: dict) -> bytes:
    """One JSON object as bytes (no separator: the peer frames by object)."""
    return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()
