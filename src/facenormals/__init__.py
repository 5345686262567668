"""facenormals: differentiable ops for reconstructing 3D heads from normals and landmarks."""

__version__ = "0.1.0"
