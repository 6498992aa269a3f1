"""Where the real recordings of the project's shared folder are (tests that read them are
skipped with a reason where they are absent).

``COMO3R_SHARED_DATA`` names the folder; otherwise ``shared/data`` beside the checkout (as CI
lays it out), then ``/work/shared/data``.
"""

from __future__ import annotations

import os
from pathlib import Path


def _shared_data() -> Path:
    candidates = (
        [Path(os.environ["COMO3R_SHARED_DATA"])] if "COMO3R_SHARED_DATA" in os.environ else []
    )
    candidates += [
        Path(__file__).resolve().parents[3] / "shared" / "data",
        Path("/work/shared/data"),
    ]
    return next((path for path in candidates if path.is_dir()), candidates[0])


SHARED_DATA = _shared_data()
