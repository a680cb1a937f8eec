"""The stopping rule of an iteration that contracts, shared by the element's root finder
(``_solve._converged``) and the tangent's Richardson iteration (``_tangent._iterated``)."""


def error_left_below(step, theta, limit):
    """The updates after one of size ``step``, at the contraction rate ``theta`` (the ratio of
    the last two), add up to about ``step theta / (1 - theta)``: below ``limit``, for a rate
    that contracts (theta <= 1/2)."""
    return (theta <= 0.5) & (step * theta <= (1.0 - theta) * limit)
