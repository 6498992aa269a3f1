"""como3r: collaborative monocular dense SLAM with a learned two-view 3D prior."""

from como3r.errors import Como3rError

__version__ = "0.1.0"

__all__ = ["Como3rError", "__version__"]
