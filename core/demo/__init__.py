"""The demos: the main job on a small built-in capture (`run`), and the rasterizer alone on
ground-truth splats (`raster`)."""

from core.demo.raster import run_raster_demo
from core.demo.run import DEMO_OVERRIDES, DEMO_SYNTH, demo_capture, report, run_demo

__all__ = ["DEMO_OVERRIDES", "DEMO_SYNTH", "demo_capture", "report", "run_demo", "run_raster_demo"]
