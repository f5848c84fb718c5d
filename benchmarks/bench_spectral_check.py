"""Six channels against trichromatic (issue 51, item 4; docs/validation.md):
``python benchmarks/bench_spectral_check.py RESULT --gt SIM [--samples N]``.

RESULT is a reconstruction of the simulation SIM after its biophysical stage (``polarface reconstruct
SIM --out RESULT``, or ``--geometry SIM/ground_truth`` to take the surface out of the comparison). Prints
the median spectral RMSE of the reflectance the six-channel chromophores imply and of a trichromatic fit
of the same data, both against the simulator's true spectra, with the chromophores' errors.
"""

from __future__ import annotations

import argparse
import json

from polarface.pipeline import spectral_check


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("result", help="RESULT folder (after its biophysical stage)")
    parser.add_argument("--gt", required=True, help="the simulation folder SIM (or SIM/ground_truth)")
    parser.add_argument("--samples", type=int, default=4096, help="texels compared (drawn from the mask)")
    args = parser.parse_args()
    summary = spectral_check(args.result, args.gt, samples=args.samples)
    for key in ("six_channel", "trichromatic"):
        row = summary[key]
        chromophores = {k: round(v, 4) for k, v in row["chromophores_median_abs_error"].items()}
        relative = 100 * row["median_relative_rmse"]
        print(f"{key:13s} spectral RMSE {row['median_rmse']:.5f} ({relative:.2f} %), "
              f"chromophores {json.dumps(chromophores)}")
    print(f"trichromatic / six-channel: {summary['trichromatic_over_six_channel']:.3f} "
          f"over {summary['texels']} texels")


if __name__ == "__main__":
    main()
