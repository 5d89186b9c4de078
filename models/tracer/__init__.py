"""Gaussian ray tracer (NVIDIA Warp, one kernel source for CPU and CUDA) and its PyTorch reference."""

from models.tracer._torch_impl import reference_trace
from models.tracer.config import TracerConfig
from models.tracer.output import LAYERS, TraceOutput
from models.tracer.tracer import Tracer

__all__ = ["Tracer", "TracerConfig", "TraceOutput", "LAYERS", "reference_trace"]
