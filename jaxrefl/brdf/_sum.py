"""Sums of BRDF components: a diffuse base plus specular lobes, assembled from parts.

f_r = sum_j f_j(p_j, wi, wo). Each component keeps its own parameters; names must not clash
(one vocabulary: the diffuse base owns ``albedo``, a specular lobe ``specular``/``alpha``...).
Reciprocity and energy conservation hold for the sum when they hold for every part (energy
conservation of a sum additionally needs the parts' albedos to add up to at most 1, which is
the caller's job; :attr:`Sum.energy_conserving` is therefore False unless there is one part).
"""

from __future__ import annotations

from jaxtyping import Array, Float

from jaxrefl._errors import JaxreflError

from ._base import BRDF, Param

__all__ = ["Sum"]


class Sum(BRDF):
    parts: tuple[BRDF, ...]

    def __init__(self, *parts: BRDF):
        if not parts:
            raise JaxreflError("Sum needs at least one component")
        names: list[str] = []
        for part in parts:
            for n in part.param_names:
                if n in names:
                    raise JaxreflError(f"parameter name {n!r} appears in two components of Sum")
                names.append(n)
        self.parts = tuple(parts)

    @property
    def params(self) -> tuple[Param, ...]:
        return tuple(q for part in self.parts for q in part.params)

    @property
    def reciprocal(self) -> bool:
        return all(part.reciprocal for part in self.parts)

    def _eval(
        self, p: dict[str, Array], wi: Float[Array, "*b 3"], wo: Float[Array, "*b 3"]
    ) -> Float[Array, "*b C"]:
        total = None
        for part in self.parts:
            f = part._eval({n: p[n] for n in part.param_names}, wi, wo)
            total = f if total is None else total + f
        assert total is not None
        return total
