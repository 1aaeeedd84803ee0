"""Relightable assets: a UV-unwrapped mesh with baked glTF PBR textures and the
learned environment as an equirectangular HDR (``glint export RUN --asset DIR``)."""
