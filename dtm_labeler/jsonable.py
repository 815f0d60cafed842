"""JSON for results and bank indexes: numpy scalars and arrays, paths and tuples."""
from __future__ import annotations

from pathlib import Path

import numpy as np


def json_default(o):
    """``json.dumps(..., default=json_default)``: numpy arrays -> lists, numpy scalars ->
    Python numbers, tuples -> lists, paths and anything else -> ``str``."""
    if isinstance(o, (np.ndarray, tuple)):
        return np.asarray(o).tolist() if isinstance(o, np.ndarray) else list(o)
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, Path):
        return str(o)
    return str(o)
