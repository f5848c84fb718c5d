"""The bundled head: the Lee Perry-Smith scan (CC BY 3.0) in millimetres with its UV-atlas maps.

Source: "Infinite, 3D Head Scan by Lee Perry-Smith" (Infinite Realities, www.ir-ltd.net, based on a
work at www.triplegangers.com), licensed CC BY 3.0 Unported, as shipped with the three.js examples
(``src/polarface/data/head/ATTRIBUTION.md``). A bust: head, neck and shoulders, 9 279 vertices,
17 684 triangles, one UV atlas.

Model frame (``docs/geometry.md``): millimetres, +y up, the face looks towards +z, +x is the subject's
left. The source (arbitrary units, bounding box +-4.28 x +-3.97 x +-2.59) is already y up / face +z; its
x extent is the shoulders. Width is measured on the cranium just above the ears (source y in
[2.0, 2.6]): 3.154 units. An adult head is about 150-155 mm broad (maximum head breadth, e.g. the
ANSUR anthropometric surveys), so one source unit is ``MM_PER_SOURCE_UNIT = 48.4`` mm: cranial breadth
152.6 mm, head length (glabella to back) ~ 213 mm, ear-to-ear including the ears ~ 175 mm, bust height
385 mm. The origin is the centre of the axis-aligned bounding box of the head (vertices above the chin,
source y > -1.0), which lies between the ears, about 12 mm above eye level.

UVs: the GLB was exported for three.js, whose TextureLoader flips images (flipY), so its raw
TEXCOORD_0 values already index the JPG maps with v up, against the glTF convention; the mesh is loaded
with ``flip_v=True`` to undo the standard glTF conversion. Maps are arrays ``(H, W, C)`` float32 on the
atlas with row 0 at v = 1 (the JPGs as they are stored), see :mod:`polarface.geometry.uv_raster`.

Maps (:class:`HeadAsset`):

* ``albedo``: ``Map-COL.jpg`` decoded from sRGB to linear (IEC 61966-2-1), RGB in [0, 1].
* ``specular``: ``Map-SPEC.jpg`` (grey, stored as data, not sRGB), ``(H, W, 1)`` in [0, 1].
* ``normal_tangent``: ``Infinite-Level_02_Tangent_SmoothUV.jpg`` as unit vectors ``2 c - 1`` in the
  tangent frame (x along +u, y along +v, z along the normal; OpenGL / three.js convention).
* ``displacement``: the scan's 4096^2 level-2 displacement JPG, 4x4 box-averaged to a 1024^2 16-bit
  PNG (bundled), converted to a height ``H`` in mm: the map holds the low-frequency difference between
  the coarse mesh and the full scan (arbitrary scale) plus mesoscale detail; we keep the detail with a
  high-pass ``d - G_sigma * d`` (Gaussian, sigma = 4 texels at 1024^2, about 1.5 mm on the cheeks) and
  scale it by ``DISPLACEMENT_MM_PER_UNIT = 4`` mm per unit of normalised map value. That gives a median
  |H| of 0.011 mm, 90th percentile 0.045 mm and 99th 0.27 mm: fine microrelief and pores tens of
  microns deep, wrinkles and lip furrows 0.1-0.3 mm, matching measured skin topography (microrelief
  20-100 um, wrinkles 0.1-0.5 mm deep; e.g. Lemperle et al. 2001, Plast. Reconstr. Surg. 108(6),
  wrinkle-assessment scale). Cross-check: on the face the slopes of H regress on the band-passed
  components of the scan's own tangent-space normal map with gains 0.85 (u) and 1.13 (v), correlation
  0.44 / 0.71, which confirms the sign (outwards), the v-up handling and the scale.

The package never reads ``../shared`` at run time; the files live in ``polarface/data/head``.
"""

from __future__ import annotations

import dataclasses
from importlib import resources
from pathlib import Path

import numpy as np

from polarface.geometry.mesh import TriangleMesh, load_mesh

__all__ = [
    "ATTRIBUTION",
    "DISPLACEMENT_MM_PER_UNIT",
    "MM_PER_SOURCE_UNIT",
    "HeadAsset",
    "head_data_dir",
    "head_placement",
    "load_head_asset",
    "pick_landmark",
    "srgb_to_linear",
]

#: One-line credit to carry into renders, simulated captures and reports derived from the asset.
ATTRIBUTION = (
    'Head scan: "Infinite, 3D Head Scan" by Lee Perry-Smith (Infinite Realities, www.ir-ltd.net), '
    "CC BY 3.0 (https://creativecommons.org/licenses/by/3.0/)"
)
#: Millimetres per source unit (cranial breadth 3.154 units -> 152.6 mm).
MM_PER_SOURCE_UNIT = 48.4
#: Height in mm per unit of the normalised (0..1) high-passed displacement map.
DISPLACEMENT_MM_PER_UNIT = 4.0
#: Gaussian sigma of the displacement high-pass, in texels of the 1024^2 map.
DISPLACEMENT_HIGHPASS_SIGMA = 4.0
#: Source y below which vertices belong to the neck/shoulders (excluded from the head's box).
_CHIN_LEVEL_SOURCE_Y = -1.0

_FILES = {
    "mesh": "LeePerrySmith.glb",
    "albedo": "Map-COL.jpg",
    "specular": "Map-SPEC.jpg",
    "normal": "Infinite-Level_02_Tangent_SmoothUV.jpg",
    "displacement": "Infinite-Level_02_Disp_NoSmoothUV-1024-16bit.png",
}

#: Approximate landmark positions (x, y) in mm in the model frame, picked on the front view of the
#: scaled asset; :func:`pick_landmark` snaps each to the front-most vertex near it.
LANDMARKS_XY_MM: dict[str, tuple[float, float]] = {
    "brow_left": (32.0, 30.0),
    "brow_right": (-32.0, 30.0),
    "forehead": (0.0, 60.0),
    "nose_tip": (0.0, -19.0),
    "mouth_left": (27.0, -53.0),
    "mouth_right": (-27.0, -53.0),
    "mouth_center": (0.0, -50.0),
    "chin": (0.0, -95.0),
    "cheek_left": (42.0, -28.0),
    "cheek_right": (-42.0, -28.0),
}


def head_placement(distance_mm: float = 1000.0) -> np.ndarray:
    """Model -> rig-world transform placing the head in front of the polarimetric module.

    The rig world (:func:`polarface.capture.rig.paper_rig`) has y down and z towards the subject;
    the model frame has y up and the face towards +z. A half turn about x makes the face look at the
    cameras; the translation puts the face (about 90 mm in front of the model origin, 10 mm below it)
    at ``distance_mm`` on the optical axis.
    """
    placement = np.diag([1.0, -1.0, -1.0, 1.0])
    placement[:3, 3] = (0.0, -10.0, distance_mm + 90.0)
    return placement


def head_data_dir() -> Path:
    """Folder of the bundled head files (inside the installed package)."""
    return Path(str(resources.files("polarface") / "data" / "head"))


def srgb_to_linear(values: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB decoding of values in [0, 1] (float) to linear [0, 1]."""
    values = np.asarray(values, dtype=np.float64)
    return np.where(values <= 0.04045, values / 12.92, ((values + 0.055) / 1.055) ** 2.4)


def pick_landmark(mesh: TriangleMesh, x: float, y: float, radius: float = 4.0) -> int:
    """Index of the front-most vertex (largest z, facing +z) within ``radius`` mm of ``(x, y)``.

    The front-facing condition (normal z > 0.2) skips the inside of the mouth and the back of the head.

    Raises:
        ValueError: if no front-facing vertex lies within ``radius`` (the radius is doubled up to 3
            times before giving up).
    """
    front = mesh.normals[:, 2] > 0.2
    dist2 = (mesh.vertices[:, 0] - x) ** 2 + (mesh.vertices[:, 1] - y) ** 2
    for scale in (1, 2, 4, 8):
        near = front & (dist2 <= (radius * scale) ** 2)
        if near.any():
            candidates = np.nonzero(near)[0]
            return int(candidates[np.argmax(mesh.vertices[candidates, 2])])
    raise ValueError(f"no front-facing vertex near (x={x}, y={y}) mm")


@dataclasses.dataclass(frozen=True, eq=False)
class HeadAsset:
    """The bundled head in mm with its maps on the UV atlas (see module docstring).

    Attributes:
        mesh: :class:`TriangleMesh` in the model frame (mm, +y up, face towards +z).
        albedo: ``(H, W, 3)`` float32 linear RGB in [0, 1].
        specular: ``(H, W, 1)`` float32 in [0, 1].
        normal_tangent: ``(H, W, 3)`` float32 unit tangent-space normals.
        displacement: ``(H, W, 1)`` float32 height H in mm (high-passed, see module docstring).
        landmarks: name -> vertex index (:data:`LANDMARKS_XY_MM`, snapped with :func:`pick_landmark`).
        neck_pivot: ``(3,)`` mm, a point on the vertical axis through the neck used by the static
            chair rotation (behind the ear line, at the head-neck joint).
    """

    mesh: TriangleMesh
    albedo: np.ndarray
    specular: np.ndarray
    normal_tangent: np.ndarray
    displacement: np.ndarray
    landmarks: dict[str, int]
    neck_pivot: np.ndarray

    def landmark_position(self, name: str) -> np.ndarray:
        """``(3,)`` mm position of landmark ``name``."""
        if name not in self.landmarks:
            raise ValueError(f"unknown landmark '{name}'; known: {sorted(self.landmarks)}")
        return self.mesh.vertices[self.landmarks[name]].copy()


def _read_rgb(path: Path) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as image:
        return np.asarray(image.convert("RGB"), dtype=np.float64) / 255.0


def _resize(image: np.ndarray, size: int | None) -> np.ndarray:
    import cv2

    if size is None or (image.shape[0] == size and image.shape[1] == size):
        return image
    interp = cv2.INTER_AREA if size < image.shape[0] else cv2.INTER_CUBIC
    out = cv2.resize(image.astype(np.float32), (size, size), interpolation=interp)
    return out.reshape(size, size, *image.shape[2:])


def load_head_asset(texture_resolution: int | None = None) -> HeadAsset:
    """Load the bundled head: mesh in mm and maps as float32 ``(H, W, C)`` arrays (v up, row 0 = top).

    Args:
        texture_resolution: ``None`` keeps the maps' native 1024^2; an int resamples every map to that
            square size (area averaging down, bicubic up; normals renormalised). Heights stay in mm.

    Raises:
        ValueError: if ``texture_resolution`` is < 1.
    """
    from scipy import ndimage

    from polarface.io.images import read_png

    if texture_resolution is not None and int(texture_resolution) < 1:
        raise ValueError(f"argument 'texture_resolution' must be >= 1; got {texture_resolution}")
    size = None if texture_resolution is None else int(texture_resolution)
    folder = head_data_dir()
    source = load_mesh(folder / _FILES["mesh"], flip_v=True)
    head = source.vertices[source.vertices[:, 1] > _CHIN_LEVEL_SOURCE_Y]
    centre = 0.5 * (head.min(axis=0) + head.max(axis=0))
    vertices = (source.vertices - centre) * MM_PER_SOURCE_UNIT
    mesh = TriangleMesh.from_arrays(vertices, source.faces, source.uv, source.normals, source="head asset")

    albedo = _resize(srgb_to_linear(_read_rgb(folder / _FILES["albedo"])), size)
    specular = _resize(_read_rgb(folder / _FILES["specular"])[..., :1], size)
    normal = _resize(_read_rgb(folder / _FILES["normal"]) * 2.0 - 1.0, size)
    normal /= np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-12)
    raw = read_png(folder / _FILES["displacement"]).astype(np.float64) / 65535.0
    detail = raw - ndimage.gaussian_filter(raw, DISPLACEMENT_HIGHPASS_SIGMA, mode="nearest")
    height = _resize(detail * DISPLACEMENT_MM_PER_UNIT, size)[..., None]

    landmarks = {name: pick_landmark(mesh, x, y) for name, (x, y) in LANDMARKS_XY_MM.items()}
    neck_pivot = np.array([0.0, -30.0, -30.0])
    return HeadAsset(
        mesh=mesh,
        albedo=np.clip(albedo, 0.0, 1.0).astype(np.float32),
        specular=np.clip(specular, 0.0, 1.0).astype(np.float32).reshape(*specular.shape[:2], 1),
        normal_tangent=normal.astype(np.float32),
        displacement=height.astype(np.float32).reshape(*height.shape[:2], 1),
        landmarks=landmarks,
        neck_pivot=neck_pivot,
    )
