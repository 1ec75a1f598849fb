"""The framed 6-DoF pose stream of the tracker: framing and record layout are pluggable, both directions.

A frame is found in the byte stream by its framing (:class:`~tandemscan.config.models.TrackerStreamConfig`):

- ``line``: one record per line, starting at the start marker (resynchronises on the next marker);
- ``length_prefixed``: a 2- or 4-byte length (``length_prefix``) before each record;
- UDP: each datagram holds whole frames in one of the framings above (:meth:`PoseStreamAdapter.feed_datagram`).

A record holds ``fields`` in order, as ``text`` (the default, one ASCII line)::

    $POSE,<frame>,<device_time_s>,<status>,<x_mm>,<y_mm>,<z_mm>,<qx>,<qy>,<qz>,<qw>,
          <sx_mm>,<sy_mm>,<sz_mm>,<srx_rad>,<sry_rad>,<srz_rad>*<XOR checksum, 2 hex digits>\\r\\n

or ``binary``: the same fields packed, ``frame`` as uint32, ``status`` as uint8 (0 = OK), the others as
float64, in ``binary_byte_order``. ``status`` is ``OK`` or e.g. ``MISSING`` (target not visible); the text
checksum is the XOR of every byte after the marker's first character up to ``*`` (NMEA style). Position in
mm, rotation as a unit quaternion (x, y, z, w) or a row-major matrix (``r00``..``r22``), 1-sigma translation
(mm) and rotation-vector (rad) uncertainty, or an ``rms_mm`` quality used for all three translation axes. A
field named ``_`` is ignored.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np
from tandemscan.config.models import TrackerStreamConfig
from tandemscan.pipeline.geometry.frames import from_quaternion, make_transform, orthonormalize, to_quaternion

KNOWN_FIELDS = {
    "frame", "device_time_s", "status", "x_mm", "y_mm", "z_mm", "qx", "qy", "qz", "qw",
    *(f"r{i}{j}" for i in range(3) for j in range(3)),
    "sx_mm", "sy_mm", "sz_mm", "srx_rad", "sry_rad", "srz_rad", "rms_mm", "_",
}
_MAX_FRAME = 4096
_DEFAULT_SIGMA_RAD = 1e-5
_PREFIX_FORMATS = {"u16le": "<H", "u16be": ">H", "u32le": "<I", "u32be": ">I"}
_BINARY_STATUS = {"OK": 0, "MISSING": 1}


class PoseFrameError(ValueError):
    """A frame that cannot be trusted: bad checksum, missing or non-numeric field, NaN, non-unit rotation."""


@dataclass(frozen=True)
class PoseSample:
    """One decoded frame: ``T_C_T`` (mm) and 6x6 covariance (mm^2, rad^2), or ``visible=False``."""

    frame: int
    device_time_s: float
    status: str
    visible: bool
    T_C_T: np.ndarray | None
    covariance: np.ndarray | None


# ---------------------------------------------------------------- framings: bytes <-> records


class LineFraming:
    """Records as lines that begin with the start marker; garbage before a marker is skipped."""

    def __init__(self, marker: bytes):
        self._marker = marker
        self._buf = bytearray()

    def split(self, data: bytes) -> list[bytes | PoseFrameError]:
        self._buf += data
        out: list[bytes | PoseFrameError] = []
        while True:
            start = self._buf.find(self._marker)
            if start < 0:
                del self._buf[: max(0, len(self._buf) - len(self._marker))]  # keep a possible partial marker
                return out
            end = self._buf.find(b"\n", start)
            if end < 0:
                del self._buf[:start]
                if len(self._buf) > _MAX_FRAME:
                    self._buf.clear()
                    out.append(PoseFrameError(f"frame longer than {_MAX_FRAME} bytes"))
                return out
            restart = self._buf.rfind(self._marker, start + 1, end)
            if restart > 0:  # a frame began before the previous one ended: that one was cut short
                del self._buf[:restart]
                out.append(PoseFrameError("truncated frame"))
                continue
            out.append(bytes(self._buf[start:end]).rstrip(b"\r"))
            del self._buf[: end + 1]

    def flush(self) -> bool:
        """Drop a partial record (end of a datagram); True if there was one."""
        partial = self._buf.find(self._marker) >= 0
        self._buf.clear()
        return partial

    def frame(self, record: bytes) -> bytes:
        return record + b"\r\n"


class LengthPrefixedFraming:
    """Records each preceded by their length (``struct`` format ``prefix``)."""

    def __init__(self, prefix: str):
        self._prefix = struct.Struct(prefix)
        self._buf = bytearray()

    def split(self, data: bytes) -> list[bytes | PoseFrameError]:
        self._buf += data
        out: list[bytes | PoseFrameError] = []
        size = self._prefix.size
        while len(self._buf) >= size:
            (n,) = self._prefix.unpack_from(self._buf)
            if n == 0 or n > _MAX_FRAME:
                self._buf.clear()  # no way to find the next frame: start over with the next bytes
                out.append(PoseFrameError(f"frame length {n} outside 1..{_MAX_FRAME} (stream out of step)"))
                break
            if len(self._buf) < size + n:
                break
            out.append(bytes(self._buf[size : size + n]))
            del self._buf[: size + n]
        return out

    def flush(self) -> bool:
        partial = bool(self._buf)
        self._buf.clear()
        return partial

    def frame(self, record: bytes) -> bytes:
        return self._prefix.pack(len(record)) + record


# ---------------------------------------------------------------- records: bytes <-> field values


class TextRecord:
    """Comma-separated ASCII fields after the start marker, with an optional XOR checksum."""

    def __init__(self, cfg: TrackerStreamConfig):
        self.cfg = cfg

    def values(self, record: bytes) -> dict[str, str | float]:
        try:
            text = record.decode("ascii")
        except UnicodeDecodeError as e:
            raise PoseFrameError("non-ASCII bytes in frame") from e
        if self.cfg.checksum:
            body, sep, check = text.rpartition("*")
            if not sep or len(check) != 2:
                raise PoseFrameError("frame without checksum")
            if f"{_xor(body[1:].encode()):02X}" != check.upper():
                raise PoseFrameError("checksum mismatch")
            text = body
        parts = text.split(",")
        if parts[0] != self.cfg.start_marker or len(parts) - 1 != len(self.cfg.fields):
            raise PoseFrameError(f"expected {len(self.cfg.fields)} fields, got {len(parts) - 1}")
        return dict(zip(self.cfg.fields, parts[1:], strict=True))

    def record(self, values: dict[str, str]) -> bytes:
        body = ",".join([self.cfg.start_marker, *(values[f] for f in self.cfg.fields)])
        if self.cfg.checksum:
            body += f"*{_xor(body[1:].encode()):02X}"
        return body.encode("ascii")


class BinaryRecord:
    """The fields packed: ``frame`` uint32, ``status`` uint8 (0 OK, 1 MISSING), the rest float64."""

    def __init__(self, cfg: TrackerStreamConfig):
        self.cfg = cfg
        codes = {"frame": "I", "status": "B", "_": "d"}
        order = "<" if cfg.binary_byte_order == "little" else ">"
        self._struct = struct.Struct(order + "".join(codes.get(f, "d") for f in cfg.fields))

    def values(self, record: bytes) -> dict[str, str | float]:
        if len(record) != self._struct.size:
            raise PoseFrameError(f"binary frame of {len(record)} bytes, expected {self._struct.size}")
        raw = dict(zip(self.cfg.fields, self._struct.unpack(record), strict=True))
        code = int(raw["status"])
        raw["status"] = next((name for name, c in _BINARY_STATUS.items() if c == code), f"STATUS{code}")
        return raw

    def record(self, values: dict[str, str]) -> bytes:
        packed = []
        for f in self.cfg.fields:
            if f == "status":
                packed.append(_BINARY_STATUS[values[f]])
            elif f == "frame":
                packed.append(int(values[f]))
            else:
                packed.append(float(values[f] or 0.0))
        return self._struct.pack(*packed)


# ---------------------------------------------------------------- the adapter


class PoseStreamAdapter:
    """Splits bytes into frames and decodes them (``feed``, ``feed_datagram``), and encodes frames
    (``encode``, for emulators), as ``cfg`` says."""

    def __init__(self, cfg: TrackerStreamConfig):
        unknown = set(cfg.fields) - KNOWN_FIELDS
        if unknown:
            raise ValueError(f"tracker stream: unknown field names {sorted(unknown)}")
        has_quat = {"qx", "qy", "qz", "qw"} <= set(cfg.fields)
        has_matrix = {f"r{i}{j}" for i in range(3) for j in range(3)} <= set(cfg.fields)
        if not ({"frame", "status", "x_mm", "y_mm", "z_mm"} <= set(cfg.fields) and (has_quat or has_matrix)):
            raise ValueError("tracker stream: fields need frame, status, x_mm, y_mm, z_mm and a rotation")
        self.cfg = cfg
        self._quat = has_quat
        self._framing = (LineFraming(cfg.start_marker.encode()) if cfg.framing == "line"
                         else LengthPrefixedFraming(_PREFIX_FORMATS[cfg.length_prefix]))
        self._record = TextRecord(cfg) if cfg.record == "text" else BinaryRecord(cfg)

    # ------------------------------------------------------------------ bytes -> samples

    def feed(self, data: bytes) -> list[PoseSample | PoseFrameError]:
        """Complete frames in ``data`` (with what was buffered), each decoded or the error it raised."""
        out: list[PoseSample | PoseFrameError] = []
        for record in self._framing.split(data):
            if isinstance(record, PoseFrameError):
                out.append(record)
                continue
            try:
                out.append(self.decode(record))
            except PoseFrameError as e:
                out.append(e)
        return out

    def feed_datagram(self, data: bytes) -> list[PoseSample | PoseFrameError]:
        """Frames of one datagram; a frame cut off at its end is an error (the next datagram starts afresh)."""
        out = self.feed(data)
        if self._framing.flush():
            out.append(PoseFrameError("truncated frame at the end of a datagram"))
        return out

    def decode(self, record: bytes) -> PoseSample:
        """One record (without framing) -> :class:`PoseSample`; :class:`PoseFrameError` if untrustworthy."""
        raw = self._record.values(record)
        status = str(raw["status"]).strip().upper()
        try:
            frame = int(raw["frame"])
            device_time = float(raw["device_time_s"]) if "device_time_s" in raw else float("nan")
        except ValueError as e:
            raise PoseFrameError(f"bad frame number or time: {e}") from e
        if status != "OK":
            return PoseSample(frame, device_time, status, False, None, None)
        num = {k: _number(k, v) for k, v in raw.items() if k not in ("status", "frame", "_")}
        t = np.array([num["x_mm"], num["y_mm"], num["z_mm"]])
        if self._quat:
            q = np.array([num["qx"], num["qy"], num["qz"], num["qw"]])
            if abs(np.linalg.norm(q) - 1.0) > 1e-3:
                raise PoseFrameError(f"quaternion norm {np.linalg.norm(q):.6f} is not 1")
            T = from_quaternion(t, q / np.linalg.norm(q))
        else:
            R = np.array([[num[f"r{i}{j}"] for j in range(3)] for i in range(3)])
            if np.abs(R @ R.T - np.eye(3)).max() > 1e-3 or np.linalg.det(R) < 0:
                raise PoseFrameError("rotation matrix is not a rotation")
            T = orthonormalize(make_transform(R, t))
        return PoseSample(frame, device_time, status, True, T, self._covariance(num))

    def _covariance(self, num: dict[str, float]) -> np.ndarray:
        if "sx_mm" in num:
            sig_t = [num["sx_mm"], num["sy_mm"], num["sz_mm"]]
        else:
            sig_t = [num.get("rms_mm", 0.0)] * 3
        sig_r = [num.get(k, _DEFAULT_SIGMA_RAD) for k in ("srx_rad", "sry_rad", "srz_rad")]
        sig = np.array(sig_t + sig_r)
        if np.any(sig < 0):
            raise PoseFrameError("negative uncertainty")
        return np.diag(sig**2)

    # ------------------------------------------------------------------ samples -> bytes

    def encode(
        self, frame: int, device_time_s: float, T_C_T: np.ndarray | None, covariance: np.ndarray | None
    ) -> bytes:
        """One framed frame as bytes; ``T_C_T=None`` encodes the target as not visible (numbers zero)."""
        values: dict[str, str] = {"frame": str(frame), "device_time_s": f"{device_time_s:.6f}", "_": ""}
        if T_C_T is None:
            values["status"] = "MISSING"
            sig = np.zeros(6)
            T = np.eye(4)
        else:
            values["status"] = "OK"
            sig = np.sqrt(np.clip(np.diag(covariance), 0, None)) if covariance is not None else np.zeros(6)
            T = np.asarray(T_C_T, float)
        t, q = to_quaternion(T)
        for key, val in zip(("x_mm", "y_mm", "z_mm"), t, strict=True):
            values[key] = f"{val:.6f}"
        for key, val in zip(("qx", "qy", "qz", "qw"), q, strict=True):
            values[key] = f"{val:.12f}"
        for i in range(3):
            for j in range(3):
                values[f"r{i}{j}"] = f"{T[i, j]:.12f}"
        for key, val in zip(("sx_mm", "sy_mm", "sz_mm", "srx_rad", "sry_rad", "srz_rad"), sig, strict=True):
            values[key] = f"{val:.3e}"
        values["rms_mm"] = f"{float(np.sqrt(np.mean(sig[:3] ** 2))):.3e}"
        return self._framing.frame(self._record.record(values))


def _number(key: str, value: str | float) -> float:
    try:
        number = float(value)
    except ValueError as e:
        raise PoseFrameError(f"field {key}={value!r} is not a number") from e
    if not np.isfinite(number):
        raise PoseFrameError(f"field {key} is {value}")
    return number


def _xor(data: bytes) -> int:
    c = 0
    for b in data:
        c ^= b
    return c
