"""The pipeline's calibrated uncertainty constants, and where their numbers come from (``calibration.json``).

Each constant is defined next to the estimator it parametrises
(`personalize.pipeline.hip`, `knee`, `foot`, `motion`); ``calibration.json``
beside this module records, per constant, its value, the benchmark and the
TRAINING phantom set it was calibrated on and the statistics measured there
(the benchmarks' own result files are not kept in the repository).
"""
from __future__ import annotations

import json
from pathlib import Path

__all__ = ["constants", "calibration_record", "CALIBRATION_FILE"]

CALIBRATION_FILE = Path(__file__).with_name("calibration.json")


def constants() -> dict:
    """Name -> value of every calibrated constant in force (numbers, or lists for matrices)."""
    import numpy as np

    from . import foot, hip, knee, motion

    out = {}
    for mod in (hip, knee, foot, motion):
        for name in mod.__all__:
            v = getattr(mod, name)
            if name.isupper() and not name.endswith("_MARKERS") and isinstance(v, (int, float, dict, tuple, np.ndarray)):
                out[name] = np.asarray(v).tolist() if isinstance(v, (np.ndarray, tuple)) else v
    return out


def calibration_record() -> dict:
    """``calibration.json``: constant name -> {value, benchmark, training_set, measured, note}."""
    return json.loads(CALIBRATION_FILE.read_text(encoding="utf-8"))["constants"]
