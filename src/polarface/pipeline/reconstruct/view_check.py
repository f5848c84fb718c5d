"""Per-view residual check of a RESULT: flag a miscalibrated camera or a wrongly posed frame.

After the polarimetric stage every view of the unwrap store (fitting and held-out) is re-rendered from
the reconstructed maps on its visible texels inside the mask, with the fit's own forward model and the
shading normals of the displaced mesh (:func:`polarface.inverse.polarimetric.fit_diagnostics`, the same
numbers as :func:`polarface.render.render_view_texture`), and per view the relative residuals

    ``i_sss_residual = RMSE(I^_sss - I_sss) / mean(I_sss)``, ``i_s_residual = RMSE(I^_s - I_s) / mean(I_sss)``

are computed over its valid samples (all three channels; the normalisation of ``evaluate``'s rerender
group, ``docs/reconstruct.md``). A view's *score* is the larger of the two. Flags
(:class:`ViewCheckConfig`, thresholds in ``docs/reconstruct.md``, "Per-view residual check and eta
uncertainty"):

* a **view** whose score is a robust outlier among all views: above ``median + k * 1.4826 * MAD`` and
  above the absolute floor ``floor``;
* a **camera** whose median view score exceeds ``ratio`` times the median score of the other cameras'
  views (and the floor): a wrong camera pose or intrinsics shows in all of its views, so it is judged
  against the other cameras rather than among views (with two cameras it is half of them);
* a **frame** whose *least* view score, each view's score first divided by its camera's median score
  (so that a bad camera does not make its worst frames look bad), exceeds ``ratio`` times the median
  of the other frames' views, with a raw median above the floor: a wrong head pose shows in every camera
  of that frame, while a bad camera's held-out frame (not fitted, so its residual grows most) shows in
  one camera only.

The same pass gives the one-sigma uncertainty of eta per texel (``maps/eta_std.exr``) and of the lobe
parameters (summarised in ``result.json``).

:func:`check_view_residuals` writes ``RESULT/view_residuals.json`` (atomic; ``docs/result_folder.md``)
and returns the summary the polarimetric stage records in ``result.json``.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import numpy as np

from polarface.io import write_json_atomic
from polarface.results import ResultFolder

__all__ = ["ETA_STD", "VIEW_RESIDUALS_JSON", "ViewCheckConfig", "check_view_residuals",
           "flag_view_residuals"]

#: File name of the per-view table under the RESULT root.
VIEW_RESIDUALS_JSON = "view_residuals.json"
#: The eta uncertainty map ``maps/eta_std.exr`` (channel ``Y``, float32, one sigma; 0 outside the mask).
ETA_STD = "eta_std"


@dataclasses.dataclass(frozen=True)
class ViewCheckConfig:
    """Thresholds of the per-view residual check (dimensionless relative residuals).

    Attributes:
        k: a view is an outlier above ``median + k * 1.4826 * MAD`` of all views' scores.
        ratio: a camera (frame) is flagged when its median score exceeds ``ratio`` x the median score of
            the other cameras' (frames') views.
        floor: no camera/frame/view flag below this score (tiny preset with the simulator's noise, 30
            iterations: all views 0.020-0.031).
    """

    k: float = 4.0
    ratio: float = 1.5
    floor: float = 0.05

    def __post_init__(self) -> None:
        for name in ("k", "ratio", "floor"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"argument 'ViewCheckConfig.{name}' must be finite and > 0; got {value}")


def _view_rows(unwrap, view_sums: np.ndarray) -> list[dict[str, Any]]:
    """One row per view: frame, camera, held-out, samples and its two relative residuals (from
    :attr:`polarface.inverse.polarimetric.FitDiagnostics.view_sums`)."""
    rows = []
    for index, view in enumerate(unwrap.views):
        sq_sss, sq_s, sum_sss, count = (float(x) for x in view_sums[index])
        row = {"view": index, "frame": int(view.frame), "camera": view.camera_id,
               "held_out": bool(view.held_out), "samples": int(count // 3)}
        if count > 0 and sum_sss > 0:
            mean_sss = sum_sss / count
            row["i_sss_residual"] = float(np.sqrt(sq_sss / count) / mean_sss)
            row["i_s_residual"] = float(np.sqrt(sq_s / count) / mean_sss)
            row["score"] = max(row["i_sss_residual"], row["i_s_residual"])
        rows.append(row)
    return rows


def _group_flags(rows: list[dict], key: str, config: ViewCheckConfig,
                 normalise: dict[str, float] | None = None) -> dict[str, dict[str, Any]]:
    """Per value of ``key`` (camera or frame): median score, the others' median and a flag with reason;
    ``normalise``: camera id -> divisor of its views' scores for the comparison."""
    scored = [r for r in rows if "score" in r]
    relative = {id(r): r["score"] / (normalise or {}).get(r["camera"], 1.0) for r in scored}
    groups: dict[str, dict[str, Any]] = {}
    for value in sorted({str(r[key]) for r in scored}, key=lambda v: (len(v), v)):
        own = [r for r in scored if str(r[key]) == value]
        other = [relative[id(r)] for r in scored if str(r[key]) != value]
        median = float(np.median([r["score"] for r in own]))
        # a frame's head pose shows in every camera: the least of its views must stand out
        compared = float((np.min if key == "frame" else np.median)([relative[id(r)] for r in own]))
        reference = float(np.median(other)) if other else None
        entry: dict[str, Any] = {"views": len(own), "median_score": median,
                                 "ratio_to_others": compared / reference if reference else None}
        if reference and median > config.floor and compared > config.ratio * reference:
            what = "rig.json pose/intrinsics" if key == "camera" else "the frame's head pose"
            entry["flag"] = (f"{key} {value}: median residual {median:.3g} is {compared / reference:.1f} x "
                             f"that of the other {key}s; check {what}")
        groups[value] = entry
    return groups


def flag_view_residuals(rows: list[dict[str, Any]], config: ViewCheckConfig | None = None) -> dict[str, Any]:
    """Flags of a per-view table (module docstring).

    Args:
        rows: per view ``{"view", "frame", "camera", "score", ...}`` (rows without ``score`` saw no texel).
        config: thresholds (default :class:`ViewCheckConfig`).

    Returns:
        ``{"threshold", "views": [flagged view rows with "reason"], "cameras": {id: ...},
        "frames": {index: ...}, "warnings": [one line per flagged camera/frame/view]}``.
    """
    config = config or ViewCheckConfig()
    scores = np.array([r["score"] for r in rows if "score" in r], np.float64)
    if scores.size == 0:
        return {"threshold": None, "views": [], "cameras": {}, "frames": {},
                "warnings": ["no view sees a reconstructed texel"]}
    median = float(np.median(scores))
    mad = float(np.median(np.abs(scores - median)))
    threshold = max(median + config.k * 1.4826 * mad, config.floor)
    flagged = []
    for row in rows:
        if row.get("score", 0.0) > threshold:
            reason = (f"view {row['view']} (frame {row['frame']}, camera {row['camera']}): residual "
                      f"{row['score']:.3g} > {threshold:.3g} (median {median:.3g} + {config.k:g} MADs)")
            flagged.append({**row, "reason": reason})
    cameras = _group_flags(rows, "camera", config)
    frames = _group_flags(rows, "frame", config, {c: g["median_score"] for c, g in cameras.items()})
    warnings = [g["flag"] for g in (*cameras.values(), *frames.values()) if "flag" in g]
    warnings += [v["reason"] for v in flagged]
    return {"threshold": threshold, "median_score": median, "mad_score": mad, "views": flagged,
            "cameras": cameras, "frames": frames, "warnings": warnings}


def check_view_residuals(folder: ResultFolder, config: ViewCheckConfig | None = None) -> dict[str, Any]:
    """Re-render every view of ``folder``'s unwrap store, write ``view_residuals.json`` and
    ``maps/eta_std.exr``; return the summary the polarimetric stage records.

    Args:
        folder: a RESULT with ``unwrap.zarr`` and the polarimetric maps (``maps/*.exr``, ``mask.png``).
        config: thresholds (default :class:`ViewCheckConfig`).

    Returns:
        ``{"views", "flagged_views", "flagged_cameras", "flagged_frames", "median_score", "threshold",
        "warnings", "uncertainty": {"<param>_std_median", ...}, "seconds"}`` (the full table is in the file).

    Raises:
        FileNotFoundError: the RESULT has no unwrap store or no polarimetric maps (naming the path).
    """
    from polarface.inverse.polarimetric import fit_diagnostics
    from polarface.texture import UnwrapStore

    started = time.perf_counter()
    config = config or ViewCheckConfig()
    if not folder.unwrap_path.exists():
        raise FileNotFoundError(f"'{folder.unwrap_path}' does not exist: the per-view residual check needs "
                                "the RESULT's unwrap store (run reconstruct's prepare stage)")
    if not folder.has_map("eta") or not folder.has_map("mask", ".png"):
        raise FileNotFoundError(f"'{folder.maps_dir}' holds no polarimetric maps (run the polarimetric "
                                "stage)")
    unwrap = UnwrapStore.open(folder.unwrap_path)
    maps = folder.read_maps(folder.channel_names())
    mask = maps.pop("mask")
    diagnostics = fit_diagnostics(unwrap, maps, mask)
    rows = _view_rows(unwrap, diagnostics.view_sums)
    flags = flag_view_residuals(rows, config)
    folder.write_scalar_map(ETA_STD, np.nan_to_num(diagnostics.std["eta"], nan=0.0).astype(np.float32))
    uncertainty = {}
    for name, values in diagnostics.std.items():
        finite = values[mask & np.isfinite(values)]
        uncertainty[f"{name}_std_median"] = float(np.median(finite)) if finite.size else None
    uncertainty["undetermined_texels"] = int((mask & ~np.isfinite(diagnostics.std["eta"])).sum())
    seconds = time.perf_counter() - started
    write_json_atomic(folder.root / VIEW_RESIDUALS_JSON, {
        "format": "polarface-view-residuals", "config": dataclasses.asdict(config),
        "normalisation": "RMSE over the view's valid samples in the mask / its mean observed I_sss",
        "rows": rows, **flags, "seconds": seconds,
    })
    return {
        "views": len(rows),
        "flagged_views": [v["view"] for v in flags["views"]],
        "flagged_cameras": [c for c, g in flags["cameras"].items() if "flag" in g],
        "flagged_frames": [int(f) for f, g in flags["frames"].items() if "flag" in g],
        "median_score": flags.get("median_score"),
        "threshold": flags["threshold"],
        "warnings": flags["warnings"],
        "uncertainty": uncertainty,
        "seconds": seconds,
    }
