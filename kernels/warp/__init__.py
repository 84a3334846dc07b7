"""NVIDIA Warp backend: CUDA GPUs, or Warp's CPU device."""
import warp as _wp

_wp.config.quiet = True
