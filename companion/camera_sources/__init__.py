"""Camera sources (being split into a package: the next commit divides sim_transport.py by concern)."""

from companion.camera_sources.sim_transport import *  # noqa: F401,F403
from companion.camera_sources.sim_transport import SIM_HEADER, __all__  # noqa: F401
