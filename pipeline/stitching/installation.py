"""The cell's mount transforms (mm): tracker on its chassis, arm base on its chassis, scanner, target."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tandemscan.config.models import InstallationConfig
from tandemscan.pipeline.geometry import frames as F


@dataclass(frozen=True)
class Installation:
    """Mount transforms of the cell (mm): tracker on its chassis, arm base on its chassis, scanner and target.

    ``T_T_S_covariance``: the 6x6 covariance of ``T_T_S`` where a calibration measured it (translation mm^2,
    then rotation vector rad^2, of ``T_T_S -> T_T_S [R(r), t]``), else None.
    """

    T_V1_C: np.ndarray
    T_V2_B: np.ndarray
    T_E_S: np.ndarray
    T_T_S: np.ndarray
    T_T_S_covariance: np.ndarray | None = None

    @property
    def T_E_T(self) -> np.ndarray:
        """Flange to target, through the scanner: ``T_E_S inv(T_T_S)``."""
        return self.T_E_S @ F.invert(self.T_T_S)

    @classmethod
    def nominal(cls, cfg: InstallationConfig) -> Installation:
        """The CAD values of the configuration."""
        return cls(cfg.T_V1_C.matrix(), cfg.T_V2_B.matrix(), cfg.T_E_S.matrix(), cfg.T_T_S.matrix())

    def perturbed(self, rng: np.random.Generator, sigma_mm: float, sigma_rad: float) -> Installation:
        """A copy with every mount off by Gaussian errors (per axis, mm and rad), as a real build is."""

        def jitter(T: np.ndarray) -> np.ndarray:
            return T @ F.from_rotvec(rng.normal(0, sigma_mm, 3), rng.normal(0, sigma_rad, 3))

        return Installation(jitter(self.T_V1_C), jitter(self.T_V2_B), jitter(self.T_E_S), jitter(self.T_T_S))

    def to_json(self) -> dict:
        """The four matrices as nested lists (mm) and, where known, ``T_T_S_covariance`` as a calibration file
        holds it (``{"order": ..., "matrix": 6x6}``)."""
        out: dict = {k: getattr(self, k).tolist() for k in ("T_V1_C", "T_V2_B", "T_E_S", "T_T_S")}
        if self.T_T_S_covariance is not None:
            out["T_T_S_covariance"] = {"order": "translation mm, rotation vector rad; T_T_S -> T_T_S [R(r), t]",
                                       "matrix": np.asarray(self.T_T_S_covariance, float).tolist()}
        return out

    @classmethod
    def from_json(cls, data: dict) -> Installation:
        """Inverse of :meth:`to_json`; a calibration file's ``T_T_S_covariance`` (``{"matrix": 6x6}``) is read too."""
        covariance = data.get("T_T_S_covariance")
        return cls(*(np.array(data[k], float) for k in ("T_V1_C", "T_V2_B", "T_E_S", "T_T_S")),
                   T_T_S_covariance=None if covariance is None else np.array(covariance["matrix"], float))

    @classmethod
    def load(cls, path: Path) -> Installation:
        """Read an installation (calibration) JSON file with the four matrices and, if given, the covariance."""
        return cls.from_json(json.loads(Path(path).read_text(encoding="utf-8")))
