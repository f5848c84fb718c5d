"""Ray-casting and UV-raster throughput on the bundled head (run: ``python benchmarks/bench_raycast.py``).

Prints (1) Embree primary-ray throughput for a 612x512 camera 1 m in front of the head, (2) shadow-ray
throughput for 8 point lights (the rig's LED modules, 100 mm around the lens axis) from every hit,
(3) the wall time of :func:`polarface.geometry.rasterize_uv` at 1024^2 and 2048^2. Each number is the
best of ``--repeats`` runs (plus the median). Not a test: numbers depend on the machine.
"""

from __future__ import annotations

import argparse
import math
import statistics
import time

import numpy as np

from polarface.geometry import PinholeCamera, RayCaster, load_head_asset, rasterize_uv


def timed(function, repeats: int) -> tuple[float, float, object]:
    times = []
    result = None
    for _ in range(repeats):
        start = time.perf_counter()
        result = function()
        times.append(time.perf_counter() - start)
    return min(times), statistics.median(times), result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--width", type=int, default=612)
    parser.add_argument("--height", type=int, default=512)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--raster", type=int, nargs="*", default=[1024, 2048], help="texture sizes")
    args = parser.parse_args()

    asset = load_head_asset(64)
    camera = PinholeCamera.look_at(
        [0.0, 0.0, 1000.0], [0.0, 0.0, 0.0], width=args.width, height=args.height, fov_y=math.radians(22.0)
    )
    lights = np.array(
        [[100.0 * math.cos(a), 100.0 * math.sin(a), 1000.0] for a in np.arange(8) * math.pi / 4]
    )
    start = time.perf_counter()
    caster = RayCaster(asset.mesh)
    build = time.perf_counter() - start
    origins, directions = camera.pixel_rays()
    origins, directions = origins.reshape(-1, 3), directions.reshape(-1, 3)

    best, median, hits = timed(lambda: caster.first_hits(origins, directions), args.repeats)
    count = origins.shape[0]
    faces = asset.mesh.face_count
    print(f"## Embree ray casting on the head ({faces} triangles, scene build {build * 1e3:.1f} ms)")
    print("| query | rays | best s | median s | rays/s (best) |")
    print("|---|---|---|---|---|")
    size = f"{args.width}x{args.height}"
    print(f"| primary {size} | {count} | {best:.4f} | {median:.4f} | {count / best:.3e} |")
    points = hits.point[hits.hit]
    normals = hits.geometric_normal[hits.hit]
    best_s, median_s, lit = timed(lambda: caster.shadow_rays(points, normals, lights), args.repeats)
    shadow_count = lit.size
    print(
        f"| shadow, 8 lights x {points.shape[0]} hits | {shadow_count} | {best_s:.4f} | {median_s:.4f} "
        f"| {shadow_count / best_s:.3e} |"
    )
    total = count + shadow_count
    print(
        f"| frame total (primary + shadow) | {total} | {best + best_s:.4f} | {median + median_s:.4f} "
        f"| {total / (best + best_s):.3e} |"
    )
    print(f"\nhit fraction {hits.hit.mean():.3f}, lit fraction {lit.mean():.4f}")

    if args.raster:
        print("\n## UV-atlas rasterisation (rasterize_uv, per-texel geometry included)")
        print("| texture | best s | median s | coverage |")
        print("|---|---|---|---|")
        for size in args.raster:
            repeats = max(1, min(args.repeats, 3))
            best_r, median_r, raster = timed(lambda size=size: rasterize_uv(asset.mesh, size), repeats)
            print(f"| {size}x{size} | {best_r:.3f} | {median_r:.3f} | {raster.coverage:.4f} |")


if __name__ == "__main__":
    main()
