"""Backends by name: ``numpy`` (reference), ``opencl`` (pyopencl, PoCL by default), ``warp``."""
from __future__ import annotations

import importlib
import importlib.util
import inspect

from .backend import Backend
from .errors import BackendUnavailable, InputError

#: name -> (module, class, what it needs, how to get it)
BACKENDS = {
    "numpy": ("pointfence.kernels.reference.backend", "NumpyBackend", "numpy", "pip install numpy"),
    "opencl": ("pointfence.kernels.opencl.backend", "OpenCLBackend", "pyopencl and an OpenCL device",
               "pip install 'pyopencl[pocl]' (PoCL CPU device, no GPU needed)"),
    "warp": ("pointfence.kernels.warp.backend", "WarpBackend", "warp-lang and a CUDA GPU (or Warp's CPU device)",
             "pip install 'pointfence[warp]' (warp-lang)"),
}

DEFAULT_BACKEND = "opencl"


def get_backend(name: str | None = None, device: str | None = None, **options) -> Backend:
    """The backend called ``name`` on ``device`` (backend-specific device spec, None = default);
    ``options`` go to the backend's constructor (``warp``: ``tuning``, a ``WarpTuning``;
    ``opencl``: ``inline``)."""
    name = (name or DEFAULT_BACKEND).strip().lower()
    if name not in BACKENDS:
        raise BackendUnavailable(f"unknown backend {name!r}; available: {', '.join(available())}; known: {', '.join(BACKENDS)}")
    module, cls, needs, how = BACKENDS[name]
    if importlib.util.find_spec(module.rsplit(".", 1)[0]) is None:
        raise BackendUnavailable(
            f"backend {name!r} is not part of this version of pointfence; available: {', '.join(available())}"
        )
    try:
        mod = importlib.import_module(module)
    except ImportError as e:
        raise BackendUnavailable(
            f"backend {name!r} is not available here ({e}); it needs {needs}: {how}. "
            f"Available now: {', '.join(available()) or 'none'}"
        ) from None
    backend_cls = getattr(mod, cls)
    unknown = sorted(set(options) - set(inspect.signature(backend_cls).parameters) - {"device"})
    if unknown:
        takes = [p for p in inspect.signature(backend_cls).parameters if p != "device"]
        raise InputError(f"backend {name!r} has no option {', '.join(unknown)}; "
                         f"its options: {', '.join(takes) or 'none'}")
    return backend_cls(device, **options)


def available() -> list:
    """Names of the backends whose modules import here (devices are checked on use)."""
    out = []
    for name, (module, *_rest) in BACKENDS.items():
        try:
            importlib.import_module(module)
        except ImportError:  # the backend's package or its dependency is missing
            continue
        out.append(name)
    return out
