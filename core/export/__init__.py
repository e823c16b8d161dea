"""Delivering a run (`dgs export`): frame PLYs, SPZ per frame, and the relightable sequence
stream (`.dgss`, docs/stream.md) that the web page's player fetches by HTTP ranges."""

from core.export.codec import StreamConfig
from core.export.container import StreamError
from core.export.splats import Splats, read_frame_ply, write_frame_ply
from core.export.spz import SPZ_BOUNDS, read_spz, write_spz

__all__ = ["SPZ_BOUNDS", "Splats", "StreamConfig", "StreamError", "read_frame_ply", "read_spz",
           "write_frame_ply", "write_spz"]
