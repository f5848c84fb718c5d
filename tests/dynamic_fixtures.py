"""Small fake RESULTs for the dynamic stage's tests (importable: ``tests`` is on pytest's ``pythonpath``): a
dynamic RESULT for the report tests, a static one for the input checks, and a folder snapshot."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from disk_fixtures import plane_mesh
from polarface.capture import SIX_CHANNEL_NAMES
from polarface.geometry import save_obj
from polarface.io import record_path, write_png
from polarface.results import ResultFolder
from polarface.results.fingerprint import capture_identity

__all__ = ["C_H_OUT", "DROP", "RES", "STEP_S", "fake_static_result", "snapshot", "write_dynamic_result"]

RES = 32
#: Frame spacing (s) of the fakes, as in the demo preset.
STEP_S = 0.2
#: Outer haemoglobin of the fakes outside the pressed blob, and its drop at the blob's centre in frame 0.
C_H_OUT, DROP = 0.05, 0.03


def _blob(centre: tuple[float, float], sigma: float) -> np.ndarray:
    rows, cols = np.mgrid[0:RES, 0:RES]
    return np.exp(-0.5 * ((rows - centre[0]) ** 2 + (cols - centre[1]) ** 2) / sigma**2)


def write_dynamic_result(root: Path, frames: int = 5, failed: dict[int, str] | None = None) -> Path:
    """A dynamic RESULT of a plane: ``frames`` frames ``STEP_S`` apart; the ``failed`` ones have a folder
    without maps. C_h_out drops by ``DROP`` in a blob (sigma 3 texels) centred at texel (10, 20) and
    recovers with tau = 2/3 s; a fainter blob at (24, 6) changes 5x less; rho_sss_bar rises from 0.2
    (frame 0) to 0.4 (last frame), uniformly."""
    failed = failed or {}
    folder = ResultFolder(root)
    folder.write_result_header(SIX_CHANNEL_NAMES, (RES, RES), 2.0)
    mesh = plane_mesh()
    save_obj(root / "mesh.obj", mesh)
    folder.write_scalar_map("c_h_out", np.full((RES, RES), C_H_OUT, np.float32))
    pressed = _blob((10, 20), 3.0) + 0.2 * _blob((24, 6), 2.0)
    mask = np.zeros((RES, RES), bool)
    mask[1:-1, 1:-1] = True
    for t in range(frames):
        frame = folder.frame(t)
        frame.root.mkdir(parents=True)
        if t in failed:
            continue
        remaining = np.exp(-t * STEP_S / (2.0 / 3.0))
        frame.write_scalar_map("c_h_out", (C_H_OUT - DROP * pressed * remaining).astype(np.float32))
        for name, value in (("c_m", 0.05), ("beta_m", 0.1), ("c_h_in", 0.03)):
            frame.write_scalar_map(name, np.full((RES, RES), value, np.float32))
        albedo = 0.2 + 0.2 * t / max(frames - 1, 1)
        frame.write_channel_map("rho_sss_bar", np.full((RES, RES, 6), albedo, np.float32), SIX_CHANNEL_NAMES)
        frame.write_mask(mask)
        save_obj(frame.root / "mesh.obj", mesh)
        write_png(frame.preview_path("subsurface_srgb"), np.full((RES, RES, 3), albedo))
    done = [t for t in range(frames) if t not in failed]
    folder.record_stage("dynamic", {
        "frames": list(range(frames)), "completed": done,
        "failed_frames": {str(t): reason for t, reason in failed.items()},
        "timestamps_s": {str(t): t * STEP_S for t in range(frames)},
        "timings": {"frames": {str(t): {"total_s": 3.0 + t} for t in done}}, "seconds_per_frame": 4.5,
    })
    return root


def fake_static_result(root: Path, static_capture: Path, *, polarimetric: bool = True) -> Path:
    """A RESULT whose files pass the dynamic stage's check of a static result (rig, mesh, eta, mask,
    polarimetric stage complete; with ``polarimetric`` False that stage is not recorded) and whose records
    name ``static_capture`` as the capture it was reconstructed from (its files, not a reconstruction)."""
    folder = ResultFolder(root)
    root.mkdir(parents=True)
    folder.write_result_header(SIX_CHANNEL_NAMES, (8, 8), 1.0)
    shutil.copyfile(static_capture / "rig.json", root / "rig.json")
    save_obj(root / "mesh.obj", plane_mesh())
    folder.write_scalar_map("eta", np.full((8, 8), 1.4, np.float32))
    folder.write_mask(np.ones((8, 8), bool))
    folder.update_result({"fingerprint": {"capture": capture_identity(static_capture)}})
    folder.record_stage("prepare", {"capture": record_path(root, static_capture)})
    if polarimetric:
        folder.record_stage("polarimetric", {})
    return root


def snapshot(root: Path) -> dict[str, tuple[int, int]]:
    """Every file under ``root``: size and mtime (to check that nothing was written or removed)."""
    return {str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns)
            for p in sorted(root.rglob("*")) if p.is_file()}
