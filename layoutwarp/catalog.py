"""What the command line lists before it imports anything heavy: the built-in layout families by
name, and the two-parameter ones (the axes of a θ-landscape). The classes are in
[`FAMILIES`][layoutwarp.layouts.base.FAMILIES], which also holds any family a user registers; tests check that
the names here are its built-in ones."""

from __future__ import annotations

__all__ = ["BUILTIN_FAMILIES", "TWO_PARAMETER_FAMILIES"]

#: The families layoutwarp registers, in the order the command line lists them.
BUILTIN_FAMILIES = ("uniform", "rect", "curv", "fovea", "elliptic", "spline", "grid")
#: The families whose layouts have exactly two parameters (θx, θy) by default.
TWO_PARAMETER_FAMILIES = ("rect", "curv", "elliptic")
