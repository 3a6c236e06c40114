"""Synthetic marker-room videos with known truth: the renderer behind `annotator simulate`."""

from annotator.render.camera import CameraModel, default_cameras
from annotator.render.experiment import RenderResult, render_experiment
from annotator.render.trajectory import LoopTrajectory

__all__ = ["CameraModel", "LoopTrajectory", "RenderResult", "default_cameras", "render_experiment"]
