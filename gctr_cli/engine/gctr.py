"""Placeholder while the engine is written (replaced in the next commit)."""
from __future__ import annotations

import numpy as np

from gctr_cli.config import EngineConfig
from gctr_cli.engine.result import RegistrationResult


def register(source: np.ndarray, target: np.ndarray, config: EngineConfig | None = None, seed: int = 0, *,
             source_normals: np.ndarray | None = None, target_normals: np.ndarray | None = None) -> RegistrationResult:
    raise NotImplementedError
