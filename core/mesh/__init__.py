"""Meshes of reconstructed frames (docs/design.md section 5, Mesh): TSDF fusion of the geometry
branch's depth, marching cubes, cleanup, vertex colours, PLY/OBJ/GLB export in the capture's
original coordinates, and accuracy against reference meshes."""

from core.mesh.build import appearance_model, mesh_model, scene_box
from core.mesh.metrics import mesh_distance
from core.mesh.run import mesh_run, source_from_world, training_views
from core.mesh.surface import FORMATS, clean_mesh, export_mesh, extract_surface, transform_mesh
from core.mesh.tsdf import TSDFVolume

__all__ = [
    "FORMATS",
    "TSDFVolume",
    "appearance_model",
    "clean_mesh",
    "export_mesh",
    "extract_surface",
    "mesh_distance",
    "mesh_model",
    "mesh_run",
    "scene_box",
    "source_from_world",
    "training_views",
]
