"""The JSON that ``hoisdf score --out`` and ``python -m hoisdf.evaluate`` write: NaN and infinity become ``null``
(strict JSON has neither), numpy scalars plain numbers."""

from __future__ import annotations

import numpy as np


def json_safe(x):
    """JSON-safe copy: NaN/inf -> None, numpy scalars -> Python."""
    if isinstance(x, dict):
        return {str(k): json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    if isinstance(x, (float, np.floating)):
        return float(x) if np.isfinite(x) else None
    return x.item() if isinstance(x, np.generic) else x
