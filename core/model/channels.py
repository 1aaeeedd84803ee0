"""Names of the per-pixel channels a render can show (reports, renders/, the viewer).

Kept free of heavy imports so the API and viewer protocol can name channels without
loading torch.
"""

CHANNELS = ("final", "base", "specular", "normal", "depth", "w_r", "roughness", "alpha")
