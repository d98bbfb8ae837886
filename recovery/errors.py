"""Exceptions the recovery code raises, each naming the rule that failed."""

from __future__ import annotations

__all__ = ["RecoveryError", "ModelDimensionError", "InsufficientSurfaceVariation", "InputError"]


class RecoveryError(ValueError):
    """Base class: the data or the request cannot support the computation."""

    code = "recovery_error"


class ModelDimensionError(RecoveryError):
    """D(S) >= C or D(E) > D(S) + 1 (Wandell 1985, 'A condition on the number
    of color sensors' and eq. 35)."""

    code = "model_dimensions"


class InsufficientSurfaceVariation(RecoveryError):
    """Too few independent surfaces to define the subspace (Wandell 1985,
    eq. 30: at least D(S) independent sensor vectors are needed)."""

    code = "insufficient_surface_variation"


class InputError(RecoveryError):
    """The image or an option is malformed (shape, channels, values)."""

    code = "bad_input"
