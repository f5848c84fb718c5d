"""Accuracy and cost of the photometric surface refinement (docs/geometry.md, step 5; issue 49).

``python benchmarks/bench_surface_refinement.py SIM [--geometry GEOM] [--cases truth,pushed,poses]``

SIM is a simulation (e.g. the demo's ``demo_out/sim``; the refinement needs the demo's resolution: the
``tiny`` preset does not resolve it). Cases, each printed as one JSON line:

* ``truth``: the true rest mesh refined with the true poses: how far the measurement's noise moves a
  surface that is already right (measured texels' and vertices' offsets, mm);
* ``pushed``: the true mesh with a disc of 30 mm radius on the forehead pushed 0.5 mm outwards along
  its normals: the median residual of its inner 20 mm after the refinement (0 = pulled back exactly);
* ``poses``: the frame scores with one frame's pose turned and shifted (0.3 deg, 1 deg, 4 deg + 3 mm,
  10 deg + 20 mm): its score over the median and whether it was flagged;
* with ``--geometry GEOM`` (a ``polarface geometry --no-surface-refinement`` folder of SIM's static
  sequence): its reference mesh refined with its poses, the median / p95 distance to the true surface
  before and after (reference frame, mm) and the seconds.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from polarface.capture.store import CaptureStore
from polarface.geometry.mesh import TriangleMesh, load_mesh, sample_surface
from polarface.geometry.poses import invert_rigid, load_poses, rotation_from_euler
from polarface.geometry.raycast import closest_surface_points
from polarface.geometry.uv_raster import rasterize_uv
from polarface.texture.photometric import (
    SurfaceRefinementConfig,
    TexelGrid,
    photo_consistency_volume,
    refine_surface,
)


def _stats(values: np.ndarray) -> dict[str, float]:
    values = np.abs(values)
    return {"median": round(float(np.median(values)), 4), "p95": round(float(np.percentile(values, 95)), 4)}


def _truth_case(store: CaptureStore, mesh: TriangleMesh, poses: dict[int, np.ndarray]) -> dict:
    result = refine_surface(store, mesh, poses)
    return {
        "case": "truth",
        "applied": result.applied,
        "measured_fraction": round(result.measured_fraction, 3),
        "texel_offset_mm": _stats(result.offset_mm[result.measured]),
        "vertex_offset_mm": _stats(result.vertex_offset_mm),
        "seconds": round(result.seconds, 1),
    }


def _pushed_case(store: CaptureStore, mesh: TriangleMesh, poses: dict[int, np.ndarray]) -> dict:
    vertices = mesh.vertices
    forehead = vertices[np.argmax(vertices[:, 2] + 0.8 * vertices[:, 1])]
    distance = np.linalg.norm(vertices - forehead, axis=1)
    pushed = mesh.with_vertices(vertices + 0.5 * (distance < 30.0)[:, None] * mesh.normals)
    result = refine_surface(store, pushed, poses)
    core = distance < 20.0
    residual = np.einsum("ij,ij->i", result.mesh.vertices[core] - vertices[core], mesh.normals[core])
    return {
        "case": "pushed",
        "push_mm": 0.5,
        "applied": result.applied,
        "residual_median_mm": round(float(np.median(residual)), 4),
        "residual_abs_p95_mm": round(float(np.percentile(np.abs(residual), 95)), 4),
        "seconds": round(result.seconds, 1),
    }


def _turned(pose: np.ndarray, degrees: float, shift_mm: float) -> np.ndarray:
    """``pose`` turned by ``degrees`` about the rig's vertical axis through the model's origin and shifted
    sideways by ``shift_mm``."""
    wrong = pose.copy()
    wrong[:3, :3] = rotation_from_euler(np.deg2rad(degrees)) @ pose[:3, :3]
    wrong[0, 3] += shift_mm
    return wrong


def _poses_case(store: CaptureStore, mesh: TriangleMesh, poses: dict[int, np.ndarray]) -> list[dict]:
    config = SurfaceRefinementConfig()
    grid = TexelGrid.from_raster(rasterize_uv(mesh, config.sampling.texture_size(None)))
    frame = sorted(poses)[len(poses) // 3]
    rows = []
    for degrees, shift in ((0.3, 0.0), (1.0, 0.0), (4.0, 3.0), (10.0, 20.0)):
        consistency = photo_consistency_volume(
            store, mesh, {**poses, frame: _turned(poses[frame], degrees, shift)}, grid, config
        )
        scores = consistency.frame_scores
        rows.append(
            {
                "case": "poses",
                "frame": frame,
                "turn_deg": degrees,
                "shift_mm": shift,
                "score_over_median": round(scores[frame] / float(np.median(list(scores.values()))), 3),
                "others_min_over_median": round(
                    min(s for f, s in scores.items() if f != frame) / float(np.median(list(scores.values()))),
                    3,
                ),
                "flagged": frame in consistency.flagged_frames,
            }
        )
    return rows


def _distance(mesh: TriangleMesh, truth: TriangleMesh, reference_pose: np.ndarray) -> dict[str, float]:
    samples, _ = sample_surface(mesh.vertices, mesh.faces, 200_000, 0)
    to_model = invert_rigid(reference_pose)
    distance = closest_surface_points(
        truth.vertices, truth.faces, samples @ to_model[:3, :3].T + to_model[:3, 3]
    )
    return _stats(distance.distance)


def _geometry_case(store: CaptureStore, geometry: Path, truth: TriangleMesh, true_poses: np.ndarray) -> dict:
    summary = json.loads((geometry / "geometry.json").read_text(encoding="utf-8"))
    reference = int(summary["reference_frame"])
    rejected = {int(f) for f in summary.get("rejected_frames", {})}
    mesh, poses = load_mesh(geometry / "mesh.obj"), load_poses(geometry / "poses.json")
    accepted = {r.index: poses[r.index] for r in store.frames if r.index not in rejected}
    started = time.perf_counter()
    result = refine_surface(store, mesh, accepted)
    return {
        "case": "geometry",
        "before_mm": _distance(mesh, truth, true_poses[reference]),
        "after_mm": _distance(result.mesh, truth, true_poses[reference]),
        "applied": result.applied,
        "flagged_frames": list(result.flagged_frames),
        "seconds": round(time.perf_counter() - started, 1),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sim", type=Path, help="simulation folder (static sequence and ground truth)")
    parser.add_argument("--geometry", type=Path, help="a geometry folder of SIM's static sequence, unrefined")
    parser.add_argument("--cases", default="truth,pushed,poses", help="comma-separated: truth, pushed, poses")
    args = parser.parse_args()
    store = CaptureStore.open(args.sim / "static")
    truth = load_mesh(args.sim / "ground_truth" / "mesh_rest.obj")
    true_poses = load_poses(args.sim / "ground_truth" / "static" / "poses.json")
    poses = {record.index: true_poses[record.index] for record in store.frames}
    cases = {"truth": _truth_case, "pushed": _pushed_case, "poses": _poses_case}
    for name in filter(None, args.cases.split(",")):
        if name not in cases:
            parser.error(f"--cases: unknown case {name!r} (choose from {', '.join(cases)})")
        rows = cases[name](store, truth, poses)
        for row in rows if isinstance(rows, list) else [rows]:
            print(json.dumps(row), flush=True)
    if args.geometry is not None:
        print(json.dumps(_geometry_case(store, args.geometry, truth, true_poses)), flush=True)


if __name__ == "__main__":
    main()
