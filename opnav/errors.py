"""Typed exceptions. Every message names the file, frame or parameter at fault."""


class OpnavError(Exception):
    """Base class of every error opnav raises on purpose."""


class InputError(OpnavError, ValueError):
    """A value passed in (argument, file field, CLI option) is malformed or out of range."""


class EphemerisError(OpnavError, ValueError):
    """An ephemeris cannot answer: unknown body, epoch outside the kernel, unreadable kernel."""


class CatalogError(OpnavError):
    """The star catalog is missing, corrupt, or cannot answer the query."""


class ConvergenceError(OpnavError, RuntimeError):
    """An iteration (light time, integrator, least squares) did not converge."""


class CovarianceError(OpnavError, ValueError):
    """A covariance matrix is not symmetric positive definite (or contains NaN)."""


class FrameError(OpnavError, ValueError):
    """An image frame is unreadable, empty or otherwise unusable."""


class NoSolutionError(OpnavError):
    """An estimator found no solution that passes verification (e.g. star ID)."""
