"""The live view of a run (`hil run --view`, `hil fc --view`) and the replay of a finished one
(`hil view RUN_DIR`): one page on loopback, served with the standard library."""

from hil.view.live import LiveSource
from hil.view.server import ViewServer

__all__ = ["LiveSource", "ViewServer"]
