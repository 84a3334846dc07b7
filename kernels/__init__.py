"""Compute kernels: the frame pipeline, the spatial hash and its queries, per backend.

>>> from pointfence.kernels import get_backend, PipelineParams
>>> pipe = get_backend("opencl").pipeline(cameras, PipelineParams())
>>> pipe.ingest(frames); pipe.neighbors(queries, radius=0.01)
"""
from .backend import Backend, FramePipeline, IngestInfo
from .camera import Camera, NoiseModel
from .errors import BackendUnavailable, InputError, KernelError, PointfenceError
from .frame import DepthFrame
from .params import PipelineParams, RadiusModel, Selection, Workspace
from .registry import BACKENDS, available, get_backend

__all__ = [
    "Backend", "FramePipeline", "IngestInfo", "Camera", "NoiseModel", "DepthFrame", "PipelineParams",
    "RadiusModel", "Selection", "Workspace", "BACKENDS", "available", "get_backend",
    "BackendUnavailable", "InputError", "KernelError", "PointfenceError",
]
