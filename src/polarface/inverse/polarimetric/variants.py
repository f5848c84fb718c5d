"""Model variants of the static polarimetric inverse, as configurations of the one fit (issue 51).

The paper validates its model against simpler ones (Sec. 6, Table 4 and the comparison figure). Each
variant here is a set of :class:`~polarface.inverse.polarimetric.PolarimetricConfig` options over the
same data, losses and optimiser, so that a comparison measures the model and nothing else
(``polarface reconstruct --model NAME``; :data:`MODEL_VARIANTS`; docs/validation.md):

* ``paper``: the paper's model. Per texel: eta, the specular lobe (alpha_s, rho_s), the
  single-scattering lobe (alpha_ss, rho_ss), rho_sss_bar and the displacement map.
* ``no-single-scattering``: the single-scattering lobe dropped (rho_ss = 0). Table 4's first two rows
  differ by "the single-scattering parameters".
* ``homogeneous-ior``: one refractive index for the whole face, everything else per texel. Table 4's
  last row adds "a spatially varying refractive index", and the paper notes that existing face capture
  "use[s] a single refractive index value ... for the entire face region".
* ``homogeneous-ior-no-single-scattering``: both dropped, Table 4's first row (the refractive-index
  and azimuthal losses alone).
* ``riviere2020``: Riviere et al. 2020 as the paper describes and re-implemented it in its own framework:
  "homogeneous specular roughness and refractive index, no single scattering"; the specular albedo,
  rho_sss_bar and the geometry detail stay per texel.

* ``hwang2022``: Hwang et al. 2022 (Sparse Ellipsometry) as the paper characterises it (Sec. 6: "static
  polarimetric", "alternative and cluster-based optimization"): both lobes and the refractive index
  shared by the texels of each of 8 clusters of the diffuse albedo, fitted by alternating the index
  (eta free, the lobes held) and the specular lobes (eta held); rho_sss_bar and the detail per texel.
  Differences from the original, which is a pBRDF of an opaque object captured with a flash: the
  subsurface term and the geometry detail are the paper's, so that only the parameter sharing and the
  alternation differ; hard clusters rather than blended basis materials; our loss in every pass rather
  than their separate index and specular losses and their SQP solver; 8 clusters is our choice.

A homogeneous map is fitted in two passes (``PolarimetricConfig.homogeneous``): first free per texel,
then held at the first fit's median over the face. Clustered maps are fitted in passes too
(``PolarimetricConfig.clustered``; :mod:`polarface.inverse.polarimetric.clusters`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

from polarface.inverse.polarimetric.config import CLUSTERABLE

__all__ = ["MODEL_VARIANTS", "ModelVariant", "model_fit_options", "model_name"]


@dataclasses.dataclass(frozen=True)
class ModelVariant:
    """One model variant.

    Attributes:
        name: its name (``reconstruct --model``).
        description: what it keeps and what it drops, and from which paper.
        fit_options: the :class:`~polarface.inverse.polarimetric.PolarimetricConfig` options it sets.
    """

    name: str
    description: str
    fit_options: Mapping[str, Any]


#: The model variants, by name (``paper`` first: the default).
MODEL_VARIANTS: dict[str, ModelVariant] = {
    variant.name: variant
    for variant in (
        ModelVariant("paper", "the paper's model: every parameter per texel, two lobes (Table 4, row 3)", {}),
        ModelVariant(
            "no-single-scattering",
            "the single-scattering lobe dropped (rho_ss = 0); the rest per texel",
            {"lobes": "one"},
        ),
        ModelVariant(
            "homogeneous-ior",
            "one refractive index for the face; the rest per texel (Table 4, row 2)",
            {"homogeneous": ("eta",)},
        ),
        ModelVariant(
            "homogeneous-ior-no-single-scattering",
            "one refractive index for the face and no single-scattering lobe; the rest per texel (Table 4, "
            "row 1)",
            {"lobes": "one", "homogeneous": ("eta",)},
        ),
        ModelVariant(
            "riviere2020",
            "Riviere et al. 2020 as the paper re-implements it: homogeneous specular roughness and "
            "refractive index, no single scattering; specular albedo, diffuse albedo and detail per texel",
            {"lobes": "one", "homogeneous": ("eta", "alpha_s")},
        ),
        ModelVariant(
            "hwang2022",
            "Hwang et al. 2022 as the paper characterises it: both lobes and the refractive index shared "
            "within 8 clusters of the diffuse albedo, fitted by alternating the index and the lobes; "
            "diffuse albedo and detail per texel",
            {"clustered": CLUSTERABLE},
        ),
    )
}


def model_fit_options(name: str, fit_options: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """``fit_options`` (None: none) with the model variant ``name``'s options over them.

    Raises:
        ValueError: an unknown variant, or ``fit_options`` setting one of the variant's options to
            another value (naming both).
    """
    if name not in MODEL_VARIANTS:
        raise ValueError(f"argument '--model' must be one of {sorted(MODEL_VARIANTS)}; got {name!r}")
    options = dict(fit_options or {})
    for key, value in MODEL_VARIANTS[name].fit_options.items():
        if key in options and options[key] != value:
            raise ValueError(f"argument '--model {name}' sets {key}={value!r}, which the options given "
                             f"set to {options[key]!r}")
        options[key] = value
    return options


def model_name(config: Any) -> str | None:
    """The variant whose lobes, homogeneous and clustered maps ``config`` (a ``PolarimetricConfig``) has;
    None when they match none (a configuration made by hand)."""
    own = (config.lobes, tuple(config.homogeneous), tuple(config.clustered))
    for variant in MODEL_VARIANTS.values():
        options = variant.fit_options
        if own == (options.get("lobes", "two"), tuple(options.get("homogeneous", ())),
                   tuple(options.get("clustered", ()))):
            return variant.name
    return None
