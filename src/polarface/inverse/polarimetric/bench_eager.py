"""The eager per-texel baseline of ``polarface bench`` (:mod:`polarface.inverse.polarimetric.bench`).

The polarimetric stage's losses written the straightforward way (the style of the authors' release): a
Python loop over texels, each evaluating :func:`polarface.optics.render_polarimetric` for its views one
light at a time, with its own backward and RMSprop step (two steps per texel: it is ~1e3 times slower
than the fused kernel). :func:`eager_rate` times it in texel-view iterations per second.
"""

from __future__ import annotations

import math
import time

import torch

from polarface.inverse.polarimetric.losses import data_losses
from polarface.inverse.polarimetric.model import SamplePrediction
from polarface.inverse.polarimetric.problem import PatchProblem
from polarface.texture import ViewSpec

__all__ = ["eager_rate"]


def _eager_texel_step(samples: list[dict], params: dict[str, torch.Tensor], optimizer, scale: float) -> None:
    """One iteration of the baseline for one texel: per view, per light calls of render_polarimetric."""
    from polarface.optics.image_formation import render_polarimetric

    optimizer.zero_grad()
    eta = 1.05 + 1.45 * torch.sigmoid(params["eta"])
    alpha_s = 0.02 + 1.48 * torch.sigmoid(params["alpha_s"])
    alpha_ss = alpha_s + (1.5 - alpha_s) * torch.sigmoid(params["alpha_ss"])
    rho_s, rho_ss = 2 * torch.sigmoid(params["rho_s"]), 2 * torch.sigmoid(params["rho_ss"])
    rho = torch.sigmoid(params["rho_sss_bar"])
    normal = params["normal"] / params["normal"].norm()
    total = 0.0
    for sample in samples:
        stokes = None
        for k in range(sample["lights"].shape[0]):
            images = render_polarimetric(
                normal,
                sample["position"],
                sample["centre"],
                sample["up"],
                sample["lights"][k : k + 1],
                sample["intensity"][k : k + 1],
                eta,
                alpha_s,
                alpha_ss,
                rho_s,
                rho_ss,
                rho[sample["channels"]],
            )
            stokes = images.stokes if stokes is None else stokes + images.stokes
        s0, s1, s2 = stokes[..., 0], stokes[..., 1], stokes[..., 2]
        prediction = SamplePrediction(
            i_sss=(s0 - s1)[None], i_zeta=(-s2)[None], i_s=s1[None], specular_s1=torch.zeros_like(s1)[None]
        )
        losses = data_losses(prediction, sample["observed"][None], scale)
        total = total + losses["sss"] + losses["s"] + losses["phi"] + 0.002 * losses["psi"]
    total.backward()
    optimizer.step()


def _eager_texel_inputs(problem: PatchProblem, views: list[ViewSpec], texel: int) -> tuple[list[dict], dict]:
    """The baseline's per-view inputs and its leaf parameters for one texel of ``problem``, on the CPU
    whatever the problem's device (the eager baseline is a CPU baseline)."""
    batch = problem.batch
    chosen = torch.nonzero(batch.texel == texel)[:, 0]
    samples = []
    for s in chosen.tolist():
        view = views[int(batch.view[s])]
        samples.append(
            {
                "centre": torch.tensor(view.camera_center, dtype=torch.float32),
                "up": torch.tensor(view.camera_up, dtype=torch.float32),
                "lights": torch.tensor(view.light_positions, dtype=torch.float32),
                "intensity": torch.tensor(view.light_intensity, dtype=torch.float32),
                "channels": torch.tensor(view.channels),
                "observed": batch.observed[s].cpu(),
            }
        )
    row, col = divmod(int(texel), problem.shape[1])
    position = torch.as_tensor(problem.positions[row, col], dtype=torch.float32)
    for sample in samples:
        sample["position"] = position
    params = {
        "eta": torch.tensor(0.0, requires_grad=True),
        "alpha_s": torch.tensor(0.0, requires_grad=True),
        "alpha_ss": torch.tensor(0.0, requires_grad=True),
        "rho_s": torch.tensor(0.0, requires_grad=True),
        "rho_ss": torch.tensor(0.0, requires_grad=True),
        "rho_sss_bar": torch.zeros(6, requires_grad=True),
        "normal": problem.frame[2][row, col].detach().cpu().clone().requires_grad_(True),
    }
    return samples, params


def eager_rate(problem: PatchProblem, views: list[ViewSpec], baseline_texels: int) -> tuple[float, float]:
    """``(texel-view iterations per second, seconds)`` of the eager baseline on the first
    ``baseline_texels`` texels of ``problem`` (the rate does not depend on how many)."""
    texels = problem.batch.texel.unique()[: int(baseline_texels)]
    work, eager_s = 0, 0.0
    for texel in texels:
        samples, params = _eager_texel_inputs(problem, views, int(texel))
        optimizer = torch.optim.RMSprop(list(params.values()), lr=1e-3)
        tick = time.perf_counter()
        for _ in range(2):
            _eager_texel_step(samples, params, optimizer, problem.scale)
        eager_s += time.perf_counter() - tick
        work += 2 * len(samples)
    return (work / eager_s if eager_s > 0 else math.nan), eager_s
