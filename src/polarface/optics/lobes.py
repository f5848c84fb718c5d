"""Specular and single-scattering lobes added light by light to given Stokes vectors (the renderer's
per-light shading).

:func:`add_lobes` evaluates the lobes of :func:`polarface.optics.render_polarimetric` — the same
floating-point expressions (:func:`polarface.optics._kernels.lobe_terms`), hence the same bits — for
``K`` point lights, each times its shadow-ray visibility, without building the images and observations
of :class:`~polarface.optics.image_formation.PolarimetricImages`:

* the light-independent view geometry (exit frame, ``G1_o / cos_o``) is computed once, not per light;
* only the first ``S`` Stokes components are computed: ``S = 1`` is the first row of the Mueller chain
  ``C(-varphi~_o) F^R C(varphi~_i) s``, ``R+ s0 + R- (cos 2phi~_i s1 + sin 2phi~_i s2)``, all an RGB
  camera records; ``S = 3`` is what the four analyzer images need;
* visibility may be asked lazily (:data:`ShadowTest`) for the fragments a light reaches from the front
  only (``n . w_i > 0`` and ``n . w_o > 0`` with the shading normal, in the shading's dtype); elsewhere
  both lobes are exactly 0 (``torch.where``), so no shadow ray whose answer cannot matter is cast.

Inputs are torch tensors of one floating dtype (the shading's: float32 or float64); units and frames as
:mod:`polarface.optics.image_formation` (mm, world frame; Stokes in the camera frame). This is the
differentiable reference; the renderers use its compiled twin,
:func:`polarface.render.lobe_kernel.add_lobes_fused`, which agrees with it to float rounding (torch's
float32 ``sqrt`` is not correctly rounded: about 0.7 % of its values differ by one ulp from IEEE's).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from polarface._validation import check_range
from polarface.optics._kernels import Light, LobeView, check_geometry, lobe_terms, prepare_lights, split_xyz

__all__ = ["ShadowTest", "add_lobes", "ask_shadow_test", "checked_lobe_inputs"]

#: Lazy shadow-ray visibility for :func:`add_lobes`: ``test(k, rows)`` -> ``(len(rows),)`` bool, whether
#: light ``k`` is visible from the points ``rows`` (``(M,)`` int64 indices).
ShadowTest = Callable[[int, np.ndarray], np.ndarray]


def add_lobes(
    stokes: torch.Tensor,
    normal: torch.Tensor,
    position: torch.Tensor,
    camera_center: torch.Tensor,
    camera_up: torch.Tensor,
    light_positions: np.ndarray,
    light_intensity: torch.Tensor,
    eta: torch.Tensor,
    alpha_s: torch.Tensor,
    alpha_ss: torch.Tensor,
    rho_s: torch.Tensor,
    rho_ss: torch.Tensor,
    visible: np.ndarray | ShadowTest,
    *,
    light_stokes: torch.Tensor | None = None,
    skip_unlit: bool = True,
) -> torch.Tensor:
    """``stokes`` plus the specular and single-scattering Stokes of every visible light, ``(N, C, S)``.

    Args:
        stokes: ``(N, C, S)`` Stokes radiance to add to, ``1 <= S <= 4``: only the first ``S``
            components are computed, each the same value as in the full vector.
        normal: ``(N, 3)`` unit shading normals; position: ``(N, 3)`` mm (the dtype of the shading).
        camera_center: ``(3,)`` mm; camera_up: ``(3,)`` world up of the camera (Stokes frame).
        light_positions: ``(K, 3)`` light positions, mm (numpy, any float dtype; cast to the shading's).
        light_intensity: ``(1, C)`` radiant intensity of every light or ``(K, C)`` one row per light
            (``C = 1`` broadcasts over the channels of ``stokes``), >= 0.
        eta: ``(N, 1)`` refractive index > 1; alpha_s, alpha_ss: ``(N, 1)`` GGX roughness > 0;
            rho_s, rho_ss: ``(N, 1)`` lobe albedos >= 0 (or anything broadcasting to ``(N, C)``).
        visible: ``(N, K)`` bool visibility of each light, or a :data:`ShadowTest` asked per light for
            the points it lights from the front.
        light_stokes: ``(4,)`` or ``(K, 4)`` Stokes vector of each light in its own frame (default
            ``[1, 1, 0, 0]``).
        skip_unlit: skip lights that no point sees (they add zero).

    Raises:
        ValueError: shapes that do not match (``stokes``, ``visible`` or its answers), and, outside
            :func:`polarface._validation.trusted_inputs`, the value checks of ``render_polarimetric``.
    """
    visible, lights, intensities, polarizer = checked_lobe_inputs(
        stokes, normal, position, camera_center, camera_up, light_positions, light_intensity, eta, alpha_s,
        alpha_ss, rho_s, rho_ss, visible, light_stokes,
    )  # fmt: skip
    lazy, components = callable(visible), stokes.shape[-1]
    numpy_dtype = np.float32 if position.dtype == torch.float32 else np.float64
    normal3, position3, up3 = split_xyz(normal), split_xyz(position), split_xyz(camera_up)
    view = LobeView(normal3, position3, split_xyz(camera_center), up3, eta, alpha_s, alpha_ss)
    for k in range(lights.shape[0]):
        light = Light(lights[k], position3, normal3, up3)
        if lazy:
            lit = ask_shadow_test(visible, k, ((light.cos_i > 0.0) & (view.cos_o[..., 0] > 0.0)).numpy())
        else:
            lit = visible[:, k]
        if skip_unlit and not lit.any():
            continue
        term_s, term_ss = lobe_terms(light, view, intensities[k], polarizer[k], rho_s, rho_ss, components)
        terms = term_s + term_ss
        if not lit.all():  # 1 * x is x: multiply only where some point is shadowed
            terms = torch.from_numpy(lit.astype(numpy_dtype))[:, None, None] * terms
        stokes = stokes + terms
    return stokes


def checked_lobe_inputs(
    stokes: torch.Tensor,
    normal: torch.Tensor,
    position: torch.Tensor,
    camera_center: torch.Tensor,
    camera_up: torch.Tensor,
    light_positions: np.ndarray,
    light_intensity: torch.Tensor,
    eta: torch.Tensor,
    alpha_s: torch.Tensor,
    alpha_ss: torch.Tensor,
    rho_s: torch.Tensor,
    rho_ss: torch.Tensor,
    visible: np.ndarray | ShadowTest,
    light_stokes: torch.Tensor | None,
) -> tuple[np.ndarray | ShadowTest, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The checks of :func:`add_lobes` (its arguments); returns ``(visible`` as a bool array or the test,
    the lights ``(K, 3)``, their intensities ``(K, C')`` and polarizer states ``(K, 4)``, in the dtype of
    ``position)``. Shapes are always checked, values outside
    :func:`polarface._validation.trusted_inputs` only."""
    count, lights_count, components = position.shape[0], np.shape(light_positions)[0], stokes.shape[-1]
    if stokes.ndim != 3 or stokes.shape[0] != count or not 1 <= components <= 4:
        raise ValueError(f"argument 'stokes' must be (N, C, S) with N = {count}, 1 <= S <= 4; "
                         f"got {tuple(stokes.shape)}")
    if not callable(visible):
        visible = np.asarray(visible)
        if visible.shape != (count, lights_count) or visible.dtype != bool:
            raise ValueError(f"argument 'visible' must be (N, K) = {(count, lights_count)} bool; "
                             f"got {visible.dtype} {visible.shape}")
    dtype = position.dtype
    numpy_dtype = np.float32 if dtype == torch.float32 else np.float64
    lights = torch.from_numpy(np.asarray(light_positions, np.float64).astype(numpy_dtype))
    check_geometry(normal, position, camera_center, camera_up)
    check_range(eta, "eta", 1.0, None, low_inclusive=False)
    for name, value, inclusive in (("alpha_s", alpha_s, False), ("alpha_ss", alpha_ss, False),
                                   ("rho_s", rho_s, True), ("rho_ss", rho_ss, True)):
        check_range(value, name, 0.0, None, low_inclusive=inclusive)
    polarizer = None if light_stokes is None else torch.as_tensor(light_stokes, dtype=dtype)
    intensities, polarizer = prepare_lights(lights, light_intensity, polarizer)
    return visible, lights, intensities, polarizer


def ask_shadow_test(test: ShadowTest, light: int, front: np.ndarray) -> np.ndarray:
    """``(N,)`` bool visibility of ``light``: ``test`` asked for the ``front`` points, False elsewhere."""
    rows = np.flatnonzero(front)
    lit = np.zeros(front.shape[0], bool)
    if rows.size:
        answer = np.asarray(test(light, rows))
        if answer.shape != rows.shape or answer.dtype != bool:
            raise ValueError(f"argument 'visible' must answer {rows.shape} bool for light {light}; "
                             f"got {answer.dtype} {answer.shape}")
        lit[rows] = answer
    return lit
