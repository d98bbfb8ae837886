"""Exceptions the recovery code raises, each naming the rule that failed."""

from __future__ import annotations

__all__ = ["RecoveryError", "ModelDimensionError", "InsufficientSurfaceVariation", "InputError", "TooManyRegions"]


class RecoveryError(ValueError):
    """Base class: the data or the request cannot support the computation."""

    code = "recovery_error"

    @property
    def detail(self) -> str:
        """What was wrong, in words."""
        return str(self)


class ModelDimensionError(RecoveryError):
    """D(S) >= C or D(E) > D(S) + 1 (Wandell 1985, 'A condition on the number
    of color sensors' and eq. 35)."""

    code = "model_dimensions"


class InsufficientSurfaceVariation(RecoveryError):
    """Too few independent surfaces to define the subspace (Wandell 1985,
    eq. 30: at least D(S) independent sensor vectors are needed)."""

    code = "insufficient_surface_variation"


class InputError(RecoveryError):
    """The image, an option or a table is malformed (shape, channels,
    values); ``code`` names the rule (default ``bad_input``; e.g.
    ``bad_csv``, ``bad_color_matrix``, ``unknown_camera``)."""

    code = "bad_input"

    def __init__(self, message: str = "", code: str | None = None):
        super().__init__(message)
        if code is not None:
            self.code = code


class TooManyRegions(RecoveryError):
    """The literal light map would have more regions than the caller's limit
    (``max_regions``): its cost is linear in the regions (one eq. 30/35
    solve each, two eq. 36 solves per overlap), so a request's cost is
    bounded by refusing, not by running out of time. ``status`` is the HTTP
    status the service answers with (413: the request is too large)."""

    code = "too_many_regions"
    status = 413
