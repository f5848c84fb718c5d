"""Mitsuba round trip of a RESULT's Mitsuba export: relative RMSE of I_sss and I_s and a side-by-side figure.

    python benchmarks/export_mitsuba_comparison.py RESULT --out WORK [--spp 64] \
        [--figure docs/images/export_mitsuba_demo.png]

Exports RESULT into ``WORK/mitsuba`` (``polarface.export.mitsuba.write_mitsuba_scene``), renders the
first polarimetric camera with Mitsuba (``scalar_spectral_polarized``) and with polarface
(``polarface.export.mitsuba_check``) and prints the metrics as JSON (also ``WORK/metrics.json``). The
figure: rows I_sss and I_s; columns Mitsuba, polarface (exported parameters, local subsurface term),
their relative difference, polarface's full render. docs/export.md, section "Mitsuba 3".
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from polarface.export import ExportOptions, ExportSource
from polarface.export.mitsuba import write_mitsuba_scene
from polarface.export.mitsuba_check import compare_mitsuba_scene
from polarface.io import write_json_atomic
from polarface.render.colour import encode_srgb


def _figure(comparison, path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    face = comparison.face
    rows = (("sss", "I_sss (diffuse)"), ("s", "I_s (specular)"))
    fig, axes = plt.subplots(2, 4, figsize=(13, 6.2), constrained_layout=True)
    for row, (part, label) in enumerate(rows):
        mitsuba = comparison.mitsuba[part][..., 0]
        exported = comparison.polarface["exported"][part][..., 0]
        full = comparison.polarface["full"][part][..., 0]
        scale = np.percentile(exported[face], 99.5)
        for col, (image, name) in enumerate(
            ((mitsuba, "Mitsuba 3"), (exported, "polarface, exported maps"), (full, "polarface, full RESULT"))
        ):
            ax = axes[row, col if col < 2 else 3]
            ax.imshow(encode_srgb(image / scale))
            ax.set_title(f"{label}: {name}", fontsize=9)
        luminance_m, luminance_p = mitsuba.mean(-1), exported.mean(-1)
        difference = np.where(
            face, (luminance_m - luminance_p) / max(np.percentile(luminance_p[face], 50), 1e-12), 0
        )
        shown = axes[row, 2].imshow(difference, cmap="RdBu_r", vmin=-0.5, vmax=0.5)
        metric = comparison.metrics[f"exported.{part}.S0"]
        axes[row, 2].set_title(f"(Mitsuba - polarface) / median; rel. RMSE {metric:.3f}", fontsize=9)
        fig.colorbar(shown, ax=axes[row, 2], shrink=0.8)
    for ax in axes.flat:
        ax.set_axis_off()
    fig.suptitle(title, fontsize=10)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("result")
    parser.add_argument("--out", required=True, help="work folder (created; must not exist)")
    parser.add_argument("--spp", type=int, default=64)
    parser.add_argument("--figure", default=None)
    args = parser.parse_args()
    work = Path(args.out)
    work.mkdir(parents=True)
    source = ExportSource.open(args.result)
    tick = time.perf_counter()
    record = write_mitsuba_scene(source, work / "mitsuba", ExportOptions(formats=("mitsuba",)))
    export_s = time.perf_counter() - tick
    tick = time.perf_counter()
    comparison = compare_mitsuba_scene(source, work / "mitsuba", spp=args.spp)
    compare_s = time.perf_counter() - tick
    face = comparison.face
    means = {
        f"{ref}.{part}.mean_S0_rgb": comparison.polarface[ref][part][face][..., 0].mean(0).tolist()
        for ref in ("exported", "full")
        for part in ("sss", "s")
    }
    means.update(
        {
            f"mitsuba.{part}.mean_S0_rgb": comparison.mitsuba[part][face][..., 0].mean(0).tolist()
            for part in ("sss", "s")
        }
    )
    summary = {
        "result": str(args.result),
        "spp": args.spp,
        "face_pixels": int(face.sum()),
        "constants": record["constants"],
        "metrics": comparison.metrics,
        "means": means,
        "export_s": export_s,
        "compare_s": compare_s,
    }
    write_json_atomic(work / "metrics.json", summary)
    print(json.dumps(summary, indent=1))
    if args.figure:
        _figure(
            comparison, Path(args.figure), f"Mitsuba 3 round trip of {Path(args.result).name}, {args.spp} spp"
        )


if __name__ == "__main__":
    main()
