"""Exceptions raised by pointfence's kernels and the code around them."""


class PointfenceError(Exception):
    """Base class of every error pointfence raises on purpose."""


class InputError(PointfenceError, ValueError):
    """An input (array, parameter, transform, file) is not what is expected; the message says which."""


class BackendUnavailable(PointfenceError, RuntimeError):
    """A compute backend or device was asked for but cannot be used here."""


class KernelError(PointfenceError, RuntimeError):
    """A compute kernel failed; the caller must treat its outputs as invalid."""


class ConflictError(PointfenceError, RuntimeError):
    """A request is valid but the current state refuses it (nothing changed); the message says why
    and what to do first."""
