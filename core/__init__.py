"""Glint engine: cameras, scenes, planar Gaussians, rasterisers, G-buffer, shading.

Nothing in ``core`` imports the web, queue or viewer layers; they import it.
"""

__version__ = "0.1.0"
