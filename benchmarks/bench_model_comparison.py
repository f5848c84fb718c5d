"""The paper's model against its variants on the validation camera (issue 51; docs/validation.md):
``python benchmarks/bench_model_comparison.py --out DIR [--preset demo] [--geometry stereo|known]
[--models paper,riviere2020,...] [--no-single-scattering] [--iterations N]``.

Simulates one capture (static sequence), reconstructs it with each model variant on the same geometry,
scores every RESULT on the validation camera, prints the table, the analogue of Table 4 and the
comparison's ratios, and writes ``DIR/comparison.json``. Reruns resume (finished RESULTs are kept).
"""

from __future__ import annotations

import argparse

from polarface.inverse.polarimetric import MODEL_VARIANTS
from polarface.pipeline import ComparisonConfig, compare_models, format_comparison


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, help="work folder (simulation, one RESULT per model)")
    parser.add_argument("--preset", default="demo", choices=("tiny", "demo"), help="simulation preset")
    parser.add_argument("--geometry", default="stereo", choices=("stereo", "known"),
                        help="stereo (the user's path) or the ground-truth surface (the models alone)")
    parser.add_argument("--models", default=",".join(MODEL_VARIANTS), help="comma list of variants")
    parser.add_argument("--no-single-scattering", action="store_true",
                        help="simulate skin without the single-scattering lobe (rho_ss = 0)")
    parser.add_argument("--iterations", type=int, default=None, help="fit iterations (default: the fit's)")
    args = parser.parse_args()
    fit_options = {} if args.iterations is None else {"iterations": args.iterations}
    config = ComparisonConfig(
        preset=args.preset, models=tuple(m.strip() for m in args.models.split(",") if m.strip()),
        geometry=args.geometry, single_scattering=not args.no_single_scattering, fit_options=fit_options,
    )
    print(format_comparison(compare_models(args.out, config)))


if __name__ == "__main__":
    main()
