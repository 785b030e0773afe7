"""misrgraph: in-flight geometric calibration of MISR as a GTSAM factor graph.

Units are SI (metres, seconds, radians) inside the package; degrees and arcseconds appear only at
interfaces. See docs/ for the conventions and data model.
"""

from __future__ import annotations

from misrgraph.errors import MisrGraphError

__all__ = ["MisrGraphError", "__version__"]
__version__ = "0.1.0"
