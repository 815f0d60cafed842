"""Model files as an older build wrote them, for the tests of format compatibility."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

import numpy as np

from dtm_labeler.model.dtm import TriangulatedModel
from dtm_labeler.model.io import model_from_arrays


def as_older_format(path: Path, version: int, dropped: Callable[[str], bool]) -> TriangulatedModel:
    """The model saved at ``path`` read as a format-``version`` file: its arrays without those
    ``dropped`` names (the ones that version did not have), the header's version set to it."""
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files if not dropped(k)}
    header = json.loads(bytes(arrays["header"]).decode())
    header["format_version"] = version
    arrays["header"] = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
    return model_from_arrays(arrays, f"v{version}")
