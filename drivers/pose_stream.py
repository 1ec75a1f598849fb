"""The framed 6-DoF pose stream of the tracker: one adapter class owns the framing, both directions.

Default frame (configurable through :class:`~tandemscan.config.models.TrackerStreamConfig`), one ASCII line::

    $POSE,<frame>,<device_time_s>,<status>,<x_mm>,<y_mm>,<z_mm>,<qx>,<qy>,<qz>,<qw>,
          <sx_mm>,<sy_mm>,<sz_mm>,<srx_rad>,<sry_rad>,<srz_rad>*<XOR checksum, 2 hex digits>\\r\\n

``status`` is ``OK`` or ``MISSING`` (target not visible); the checksum is the XOR of every byte after the
marker's first character up to ``*`` (NMEA style). Position in mm, rotation as a unit quaternion (x, y, z, w) or as a row-major
matrix (fields ``r00``..``r22``), 1-sigma translation (mm) and rotation-vector (rad) uncertainty, or an
``rms_mm`` quality used for all three translation axes. A field named ``_`` is ignored.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from tandemscan.config.models import TrackerStreamConfig
from tandemscan.pipeline.frames import from_quaternion, make_transform, orthonormalize, to_quaternion

KNOWN_FIELDS = {
    "frame", "device_time_s", "status", "x_mm", "y_mm", "z_mm", "qx", "qy", "qz", "qw",
    *(f"r{i}{j}" for i in range(3) for j in range(3)),
    "sx_mm", "sy_mm", "sz_mm", "srx_rad", "sry_rad", "srz_rad", "rms_mm", "_",
}
_MAX_LINE = 4096
_DEFAULT_SIGMA_RAD = 1e-5


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


class PoseStreamAdapter:
    """Splits bytes into frames and decodes them (``feed``), and encodes frames (``encode``, for emulators)."""

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
        self._marker = cfg.start_marker.encode()
        self._buf = bytearray()

    # ------------------------------------------------------------------ bytes -> samples

    def feed(self, data: bytes) -> list[PoseSample | PoseFrameError]:
        """Complete frames in ``data`` (with what was buffered), each decoded or the error it raised."""
        self._buf += data
        out: list[PoseSample | PoseFrameError] = []
        while True:
            start = self._buf.find(self._marker)
            if start < 0:
                del self._buf[: max(0, len(self._buf) - len(self._marker))]  # keep a possible partial marker
                return out
            end = self._buf.find(b"\n", start)
            if end < 0:
                del self._buf[:start]
                if len(self._buf) > _MAX_LINE:
                    self._buf.clear()
                    out.append(PoseFrameError(f"frame longer than {_MAX_LINE} bytes"))
                return out
            restart = self._buf.rfind(self._marker, start + 1, end)
            if restart > 0:  # a frame began before the previous one ended: that one was cut short
                del self._buf[:restart]
                out.append(PoseFrameError("truncated frame"))
                continue
            line = bytes(self._buf[start:end]).rstrip(b"\r")
            del self._buf[: end + 1]
            try:
                out.append(self.decode(line))
            except PoseFrameError as e:
                out.append(e)

    def decode(self, line: bytes) -> PoseSample:
        """One frame (without the line end) -> :class:`PoseSample`; :class:`PoseFrameError` if untrustworthy."""
        try:
            text = line.decode("ascii")
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
        raw = dict(zip(self.cfg.fields, parts[1:], strict=True))
        status = raw["status"].strip().upper()
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

    def encode(self, frame: int, device_time_s: float, T_C_T: np.ndarray | None, covariance: np.ndarray | None) -> bytes:
        """One frame as bytes; ``T_C_T=None`` encodes the target as not visible (numbers zero)."""
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
        body = ",".join([self.cfg.start_marker, *(values[f] for f in self.cfg.fields)])
        if self.cfg.checksum:
            body += f"*{_xor(body[1:].encode()):02X}"
        return (body + "\r\n").encode("ascii")


def _number(key: str, text: str) -> float:
    try:
        value = float(text)
    except ValueError as e:
        raise PoseFrameError(f"field {key}={text!r} is not a number") from e
    if not np.isfinite(value):
        raise PoseFrameError(f"field {key} is {text}")
    return value


def _xor(data: bytes) -> int:
    c = 0
    for b in data:
        c ^= b
    return c
