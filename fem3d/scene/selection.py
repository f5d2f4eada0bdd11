"""What a scene selects on a body and applies there: the spec types every part of the scene
shares, the vertex selectors, and the bodies' surface and point loads (issue 43).

Part of the scene's one description (:mod:`fem3d.scene.spec` imports and re-exports every
name here; the JSON Schema of ``fem3d schema`` is the same).
"""

from __future__ import annotations

from typing import Annotated

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    StrictFloat,
    StrictInt,
    StrictStr,
    field_validator,
    model_validator,
)

__all__ = ["Vec3", "ZERO3", "Positive", "NonNegative", "Index", "LowestY", "HalfSpace",
           "Sphere", "NearVertex", "NearestTo", "Selector", "LoadKeyframe", "LoadSpec"]

Vec3 = tuple[StrictFloat, StrictFloat, StrictFloat]
ZERO3: tuple[float, float, float] = (0.0, 0.0, 0.0)
Positive = Annotated[StrictFloat, Field(gt=0)]
NonNegative = Annotated[StrictFloat, Field(ge=0)]
Index = Annotated[StrictInt, Field(ge=0)]


class _Spec(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


def _nonzero(v: Vec3, what: str = "vector") -> Vec3:
    if not any(c != 0 for c in v):
        raise ValueError(f"{what} must not be zero")
    return v


# ------------------------------------------------------------------------------ selectors
class LowestY(_Spec):
    """Vertices with ``y <= min y + tol``."""

    tol: NonNegative = 0.0


class HalfSpace(_Spec):
    """Vertices with ``(x - point) . normal >= 0``."""

    point: Vec3
    normal: Vec3

    @field_validator("normal")
    @classmethod
    def _normal(cls, v: Vec3) -> Vec3:
        return _nonzero(v, "normal")


class Sphere(_Spec):
    """Vertices with ``|x - center| <= radius``."""

    center: Vec3
    radius: NonNegative


class NearVertex(_Spec):
    """Vertices within ``radius`` of vertex ``vertex`` (body-local index)."""

    vertex: Index
    radius: NonNegative = 0.0


class NearestTo(_Spec):
    """The vertex nearest to ``point`` and every vertex within ``radius`` of it."""

    point: Vec3
    radius: NonNegative = 0.0


_SELECTOR_KEYS = ("lowest_y", "box", "half_space", "sphere", "vertices", "vertices_file",
                  "near_vertex", "nearest_to")


class Selector(_Spec):
    """Exactly one way of choosing vertices (see the module docstring)."""

    lowest_y: LowestY | None = None
    box: tuple[Vec3, Vec3] | None = None
    half_space: HalfSpace | None = None
    sphere: Sphere | None = None
    vertices: Annotated[list[Index], Field(min_length=1)] | None = None
    vertices_file: StrictStr | None = None
    near_vertex: NearVertex | None = None
    nearest_to: NearestTo | None = None

    @model_validator(mode="after")
    def _exactly_one(self) -> Selector:
        given = [k for k in _SELECTOR_KEYS if getattr(self, k) is not None]
        if len(given) != 1:
            raise ValueError(
                f"give exactly one of {', '.join(_SELECTOR_KEYS)} (got "
                f"{', '.join(given) if given else 'none'})"
            )
        if self.box is not None and any(a > b for a, b in zip(*self.box, strict=True)):
            raise ValueError("box: each min must be <= its max")
        return self

    @property
    def kind(self) -> str:
        """The selector's key (``"box"``, ...)."""
        return next(k for k in _SELECTOR_KEYS if getattr(self, k) is not None)


# ------------------------------------------------------------------------------ loads
class LoadKeyframe(_Spec):
    """The load's scale at time ``t`` (between keyframes: linear; outside: held)."""

    t: NonNegative
    scale: StrictFloat


class LoadSpec(_Spec):
    """A load on a body: a dead ``traction`` (force per unit reference area) or a follower
    ``pressure`` (on the current surface, positive pushes in) on the faces whose vertices
    ``select`` picks, or a point ``force`` split evenly over the selected vertices; scaled
    over time by ``keyframes`` (default: constant)."""

    select: Selector
    traction: Vec3 | None = None
    pressure: StrictFloat | None = None
    force: Vec3 | None = None
    keyframes: Annotated[list[LoadKeyframe], Field(min_length=1)] | None = None

    @model_validator(mode="after")
    def _one_kind(self) -> LoadSpec:
        given = [k for k in ("traction", "pressure", "force") if getattr(self, k) is not None]
        if len(given) != 1:
            raise ValueError("give exactly one of traction, pressure, force (got "
                             f"{', '.join(given) if given else 'none'})")
        frames = self.keyframes or []
        for i in range(1, len(frames)):
            if not frames[i].t > frames[i - 1].t:
                raise ValueError(f"keyframes[{i}].t = {frames[i].t:g} must be after "
                                 f"keyframes[{i - 1}].t = {frames[i - 1].t:g}")
        return self

    @property
    def kind(self) -> str:
        """``"traction"``, ``"pressure"`` or ``"force"``."""
        return next(k for k in ("traction", "pressure", "force") if getattr(self, k) is not None)
