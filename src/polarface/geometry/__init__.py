"""Geometry: meshes with UV atlases, the bundled head, cameras, Embree ray casting, UV rasterisation,
normals from heights (torch, differentiable), rigid poses and expression deformations, and geometry from
stereo: dense two-view stereo, oriented point clouds, Poisson meshing, sequence registration and the
cylindrical texture atlas.

Units mm, angles radians; cameras in the OpenCV convention; UVs v up (``docs/geometry.md``).
"""

from polarface.geometry.atlas import CylindricalAtlas, CylindricalAtlasConfig, cylindrical_atlas
from polarface.geometry.camera import PinholeCamera, distort_normalized, look_at, undistort_normalized
from polarface.geometry.deform import (
    EXPRESSIONS,
    ExpressionConfig,
    ExpressionRig,
    dynamic_sequence_weights,
    flipped_faces,
    smooth_falloff,
)
from polarface.geometry.fusion import PoissonConfig, fuse_registered, poisson_mesh
from polarface.geometry.head_asset import (
    HeadAsset,
    head_placement,
    load_head_asset,
    pick_landmark,
    srgb_to_linear,
)
from polarface.geometry.head_axis import default_axis_point, head_axis_from_poses, head_axis_point_from_poses
from polarface.geometry.heights import (
    HeightNormals,
    height_gradients,
    normals_from_height_gradients,
    normals_from_heights,
)
from polarface.geometry.mesh import (
    TriangleMesh,
    face_areas,
    face_normals,
    load_mesh,
    sample_surface,
    save_obj,
    save_ply,
    vertex_normals,
)
from polarface.geometry.point_cloud import PointCloud, VoxelAccumulator, load_point_cloud, save_point_cloud
from polarface.geometry.poses import (
    StaticSequenceConfig,
    check_rigid,
    euler_from_rotation,
    invert_rigid,
    load_poses,
    rigid_transform,
    rotation_from_euler,
    save_poses,
    static_sequence_poses,
)
from polarface.geometry.raycast import RayCaster, RayHits, embree_available
from polarface.geometry.registration import (
    RegistrationConfig,
    SequenceRegistration,
    register_sequence,
)
from polarface.geometry.stereo import (
    StereoConfig,
    StereoDepth,
    StereoRectification,
    match_stereo_pair,
    rectify_pair,
)
from polarface.geometry.tracked_file import load_tracked, save_tracked
from polarface.geometry.tracking import (
    TrackedSequence,
    TrackingConfig,
    TrackingFrame,
    track_mesh,
)
from polarface.geometry.uv_raster import (
    UVRaster,
    dilate_texture,
    rasterize_uv,
    reposition,
    sample_texture,
    texel_uv,
    texels_to_world,
)

__all__ = [
    "EXPRESSIONS",
    "CylindricalAtlas",
    "CylindricalAtlasConfig",
    "ExpressionConfig",
    "ExpressionRig",
    "HeadAsset",
    "HeightNormals",
    "PinholeCamera",
    "PointCloud",
    "PoissonConfig",
    "RayCaster",
    "RayHits",
    "RegistrationConfig",
    "SequenceRegistration",
    "StaticSequenceConfig",
    "StereoConfig",
    "StereoDepth",
    "StereoRectification",
    "TrackedSequence",
    "TrackingConfig",
    "TrackingFrame",
    "TriangleMesh",
    "UVRaster",
    "VoxelAccumulator",
    "check_rigid",
    "cylindrical_atlas",
    "default_axis_point",
    "dilate_texture",
    "distort_normalized",
    "dynamic_sequence_weights",
    "embree_available",
    "euler_from_rotation",
    "face_areas",
    "face_normals",
    "flipped_faces",
    "fuse_registered",
    "head_axis_from_poses",
    "head_axis_point_from_poses",
    "head_placement",
    "height_gradients",
    "invert_rigid",
    "load_head_asset",
    "load_mesh",
    "load_point_cloud",
    "load_poses",
    "load_tracked",
    "look_at",
    "match_stereo_pair",
    "normals_from_height_gradients",
    "normals_from_heights",
    "pick_landmark",
    "poisson_mesh",
    "rasterize_uv",
    "rectify_pair",
    "register_sequence",
    "reposition",
    "rigid_transform",
    "rotation_from_euler",
    "sample_surface",
    "sample_texture",
    "save_obj",
    "save_ply",
    "save_point_cloud",
    "save_poses",
    "save_tracked",
    "smooth_falloff",
    "srgb_to_linear",
    "static_sequence_poses",
    "texel_uv",
    "texels_to_world",
    "track_mesh",
    "undistort_normalized",
    "vertex_normals",
]
