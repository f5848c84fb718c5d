"""Benchmarks and agreement tables of polarface.skin (run: python benchmarks/bench_skin_fit.py).

Prints: the iadpython adding-doubling agreement table of the diffusion totals, SoG fit errors of the
skin layer profiles, the NIST skin-fit RMSE statistics and time, and the 1024x1024 blur timings.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import torch

from polarface.skin.fitting import fit_reflectance_spectra
from polarface.skin.heterogeneous import fit_layer_shapes
from polarface.skin.layers import layer_optics
from polarface.skin.multipole import slab_totals
from polarface.skin.sog import gaussian_blur, sog_blur
from polarface.skin.spectral import default_wavelengths

NIST = (
    Path(__file__).resolve().parents[1] / "tests" / "data" / "skin" / "nist_skin_reflectance_odd_subjects.csv"
)


def iad_table() -> None:
    import iadpython

    print("| slab | sigma_t' d | albedo | eta | R AD | R diffusion | dR % | T AD | T diffusion | dT % |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for thickness, taus in ((math.inf, (None,)), (0.25, (1.0, 2.0, 4.0, 8.0))):
        for tau in taus:
            for albedo in (0.9, 0.99, 0.999):
                for eta in (1.3, 1.4, 1.5):
                    b, d = (1e4, 1e4) if tau is None else (tau, thickness)
                    s = iadpython.Sample(a=albedo, b=b, g=0.0, d=d, n=eta, quad_pts=16)
                    ur1, ut1, _, _ = s.rt()
                    r_un, t_un = s.unscattered_rt()
                    r0 = ((eta - 1) / (eta + 1)) ** 2
                    ad_r, ad_t = (ur1 - r_un) / (1 - r0), (ut1 - float(t_un)) / (1 - r0)
                    sigma_t = b / d
                    r, t = slab_totals(sigma_t * (1 - albedo), sigma_t * albedo, thickness, eta)
                    name = "semi-inf" if tau is None else f"{thickness} mm"
                    dt = "" if tau is None else f"{100 * (t / ad_t - 1):+.1f}"
                    tt = "" if tau is None else f"{ad_t:.4f} | {t:.4f}"
                    tt = tt if tau is not None else " | "
                    print(
                        f"| {name} | {'-' if tau is None else tau} | {albedo} | {eta} | "
                        f"{ad_r:.4f} | {r:.4f} | "
                        f"{100 * (r / ad_r - 1):+.1f} | {tt} | {dt} |"
                    )


def sog_errors() -> None:
    wl = default_wavelengths()
    types = {
        "I": (0.03243, 0.09607, 0.03691, 0.01701),
        "IV": (0.08909, 0.05291, 0.02654, 0.10450),
        "mid": (0.05, 0.05, 0.03, 0.05),
    }
    print("SoG relative L2 error (min / median / max over 15 wavelengths):")
    for name, params in types.items():
        optics = layer_optics(*[torch.tensor(v, dtype=torch.float64) for v in params], wl)
        errors = fit_layer_shapes(optics).relative_error
        for layer, e in zip(("R_out^f", "T_out^f", "R_out^b", "T_out^b", "R_in^f"), errors, strict=True):
            print(f"  type {name:4s} {layer}: {e.min():.4f} / {e.median():.4f} / {e.max():.4f}")


def nist_fit() -> None:
    data = np.genfromtxt(NIST, delimiter=",", names=True)
    wl = data["wavelength_nm"]
    band = (wl >= 420) & (wl <= 700)
    names = data.dtype.names[1:]
    measured = torch.tensor(np.stack([data[n] for n in names])[:, band])
    start = time.perf_counter()
    fit = fit_reflectance_spectra(torch.tensor(wl[band]), measured)
    seconds = time.perf_counter() - start
    r = fit.rmse.numpy()
    print(
        f"NIST 50 subjects, {band.sum()} wavelengths: RMSE median {np.median(r):.4f}, p90 "
        f"{np.percentile(r, 90):.4f}, worst {r.max():.4f} ({names[int(r.argmax())]}); fit {seconds:.1f} s"
    )
    p = fit.parameters.numpy()
    for j, n in enumerate(("c_m", "beta_m", "c_h_in", "c_h_out", "offset")):
        print(f"  {n}: min {p[:, j].min():.4f} median {np.median(p[:, j]):.4f} max {p[:, j].max():.4f}")


def blur_timing() -> None:
    image = torch.rand(1024, 1024)
    weights = torch.full((9,), 1 / 9)
    for label, fn in (
        (
            "single Gaussian v=0.41 mm^2, texel 0.1 mm (2-D FFT)",
            lambda: gaussian_blur(image, 0.41, 0.1),
        ),
        (
            "single Gaussian v=6.55 mm^2, texel 0.1 mm (2-D FFT)",
            lambda: gaussian_blur(image, 6.5536, 0.1),
        ),
        ("9-Gaussian SoG, texel 0.1 mm (combined FFT)", lambda: sog_blur(image, weights, 0.1)),
        ("9-Gaussian SoG, 6 channels", lambda: sog_blur(image.expand(6, -1, -1), weights, 0.1)),
    ):
        fn()
        times = []
        for _ in range(3):
            start = time.perf_counter()
            fn()
            times.append(time.perf_counter() - start)
        print(f"  1024x1024 {label}: {min(times):.3f} s")


if __name__ == "__main__":
    torch.set_num_threads(2)
    iad_table()
    sog_errors()
    nist_fit()
    blur_timing()
