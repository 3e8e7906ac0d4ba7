# SPDX-License-Identifier: Apache-2.0
"""Figures as PNG files: one way to get pyplot (the headless Agg backend) and to save a figure.

matplotlib is imported on first use, so modules that can plot stay cheap to import.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from lompr_predictor.files import atomic_file


def pyplot() -> Any:
    """`matplotlib.pyplot` on the Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    return plt


def save_figure(figure: Any, path: str | Path, *, dpi: int = 110) -> Path:
    """Write `figure` to the PNG `path` atomically and close it (also when writing fails)."""
    path = Path(path)
    try:
        with atomic_file(path, suffix='.png') as staging:
            figure.savefig(staging, format='png', dpi=dpi)
    finally:
        pyplot().close(figure)
    return path
