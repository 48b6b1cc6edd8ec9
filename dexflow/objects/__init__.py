"""Object meshes: loading, signed distance, surface samples and convex decomposition."""

from dexflow.objects.convex import convex_decomposition, write_convex_obj
from dexflow.objects.mesh import load_mesh, write_obj
from dexflow.objects.sdf import SignedDistanceGrid, signed_distance, winding_number
from dexflow.objects.surface import sample_surface

__all__ = [
    "SignedDistanceGrid",
    "convex_decomposition",
    "load_mesh",
    "sample_surface",
    "signed_distance",
    "winding_number",
    "write_convex_obj",
    "write_obj",
]
